"""Observability of ``H``: singular values, condition number and named deficiencies."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A parameter whose 1-sigma, predicted from the noise model and the pose design, exceeds this
#: (mm for lengths, unitless for a, b, c, rad for alpha, beta) is called unidentifiable.
IDENTIFIABLE_SIGMA: dict[str, float] = {
    "x_t": 0.5, "y_t": 0.5, "z_t": 0.5, "z_t_minus_delta": 0.5, "delta": 0.5,
    "a": 0.02, "b": 0.02, "c": 0.02, "alpha": 2e-3, "beta": 2e-3,
}
#: A parameter this correlated (|rho|) with an unidentifiable one is named with it.
ENTANGLED_CORRELATION = 0.99
#: Condition number of the column-scaled, whitened regressor above which a warning is given.
CONDITION_WARNING = 1e3
#: Relative singular value below which a direction is numerically null.
NULL_TOLERANCE = 1e-9
#: What to add to the pose design so a parameter becomes identifiable.
REMEDY: dict[str, str] = {
    "a": "add poses at a second flange height so that d varies",
    "b": "add poses at a second flange height so that d varies",
    "c": "add poses at a second flange height so that d varies",
    "z_t_minus_delta": "add poses at a second flange height so that d varies",
    "alpha": "spread the spots along x",
    "beta": "spread the spots along y",
    "x_t": "add rotations about z",
    "y_t": "add rotations about z",
    "z_t": "add tilted flange orientations (rotations about x or y) or use --model schoenflies",
    "delta": "add tilted flange orientations (rotations about x or y) or use --model schoenflies",
}


@dataclass(frozen=True)
class Observability:
    """Singular values of the scaled regressor, its condition number, predicted sigmas, gaps."""

    singular_values: np.ndarray
    condition_number: float
    predicted_sigma: dict[str, float]
    unidentifiable: tuple[str, ...]

    def message(self) -> str:
        """One line naming the unidentifiable parameters and what to add.

        Without variation of ``d`` the direction (a, b, c) cannot be told from the beam point,
        so that remedy comes alone; otherwise one remedy per weak parameter.
        """
        weak = self.unidentifiable
        if {"a", "b", "c"} & set(weak):
            remedies = [REMEDY["c"]]
        else:
            remedies = list(dict.fromkeys(REMEDY[n] for n in weak))
        detail = ", ".join(f"{n} (predicted 1-sigma {self.predicted_sigma[n]:.3g})"
                           for n in weak)
        return (f"parameters not identifiable from this pose design: {detail}; "
                f"{'; '.join(remedies)}")


def analyse_observability(whitened_regressor: np.ndarray, names: tuple[str, ...]
                          ) -> Observability:
    """SVD of the whitened regressor ``A_w`` (m, p) with unit-norm columns.

    The condition number is ``s_max / s_min`` of ``A_w D`` (``D`` scales columns to unit norm);
    ``sigma_j = sqrt((A_w^T A_w)^-1)_jj`` predicts each parameter's 1-sigma from the noise model
    alone. A parameter is unidentifiable if it takes part in a null direction of ``A_w D``
    (relative singular value < 1e-9), if its predicted sigma exceeds :data:`IDENTIFIABLE_SIGMA`,
    or if it is entangled (|rho| > 0.99) with such a parameter; an unidentifiable ``c`` takes
    ``z_t - delta`` (``z_t``) with it, since the constant splits from ``c d`` only where d varies.
    """
    norms = np.linalg.norm(whitened_regressor, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    _, s, vt = np.linalg.svd(whitened_regressor / scale, full_matrices=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    bad: set[str] = {names[j] for j in np.flatnonzero(norms == 0)}
    for k in np.flatnonzero(s < NULL_TOLERANCE * s[0]):
        bad |= {names[j] for j in np.flatnonzero(np.abs(vt[k]) > 0.2)}
    normal = (whitened_regressor / scale).T @ (whitened_regressor / scale)
    cov = np.linalg.pinv(normal, rcond=1e-12) / np.outer(scale, scale)
    predicted = {n: float(np.sqrt(max(cov[j, j], 0.0))) for j, n in enumerate(names)}
    for n in names:
        if n in bad:
            predicted[n] = float("inf")
        elif predicted[n] > IDENTIFIABLE_SIGMA[n]:
            bad.add(n)
    sd = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    rho = cov / np.outer(sd, sd)
    if "c" in bad:  # z_t - delta splits from c d only where d varies
        bad |= {"z_t_minus_delta", "z_t"} & set(names)
    weak = [names.index(n) for n in bad]
    for j, n in enumerate(names):  # entangled with a weak parameter: not separable either
        if any(abs(rho[j, k]) > ENTANGLED_CORRELATION for k in weak):
            bad.add(n)
    ordered = tuple(n for n in names if n in bad)
    return Observability(s, cond, predicted, ordered)
