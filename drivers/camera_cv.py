"""Laser-spot detection and pixel -> plate mapping (OpenCV), shared by hardware and simulation.

Detection (:func:`detect_spot`), per frame:

1. background subtraction (a laser-off frame, if given);
2. coarse search: the frame is sampled every ``coarse`` pixels (``cv2.resize`` INTER_LINEAR,
   a 2 x 2 mean per sample, ten times faster than INTER_AREA) and the brightest sample found
   (``cv2.minMaxLoc``); an empty frame (peak below ``min_contrast`` grey levels or ``min_snr``
   noise sigmas above the median) is rejected;
3. a ``(2 roi_half + 1)^2`` ROI around it: saturated frames (more than ``max_saturated`` pixels
   at full scale) are rejected; intensity-weighted centroid of the pixels above
   ``centroid_threshold`` of the peak, over the ROI's border median;
4. refinement by a 2-D elliptical Gaussian fit on the ROI (Levenberg-Marquardt, analytic
   Jacobian), ``I = A exp(-(a du^2 + 2 b du dv + c dv^2) / 2) + B``, refitted with weights
   ``1 / (s_n^2 + k^2 m^2)`` when the residuals show speckle (noise proportional to the spot);
5. checks with a reason: a second spot (a residual blob in the ROI, or a coarse cell beyond
   ``3.5 sigma`` of the spot, above ``residual_ratio`` resp. ``second_ratio`` of its height), an
   elongated spot
   (axis ratio above ``max_aspect``: two merged spots), a hot pixel, a spot too wide;
6. quality ``q = snr / (snr + 10) * exp(-(misfit / 0.05)^2)`` in [0, 1] with ``snr = A / s_n``
   (``s_n`` the ROI border's noise) and ``misfit = sqrt(rms_resid^2 - s_n^2) / A``; below
   ``min_quality`` the spot is rejected as ambiguous.

Two spots closer than about 1.5 sigma merge into one slightly elongated blob and cannot be told
apart from a single spot.

Pixels (OpenCV convention, pixel centre at integer coordinates) become plate millimetres
through ``cv2.undistortPoints`` (intrinsics and distortion) then a homography fitted on a
chessboard lying on the plate (:func:`calibrate_chessboard`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from drivers.base import DriverError, SpotMeasurement


@dataclass(frozen=True)
class DetectorConfig:
    """Tuning of :func:`detect_spot` (pixels; grey levels on the frame's own scale)."""

    roi_half: int = 16
    coarse: int = 4
    min_contrast: float = 20.0
    min_snr: float = 8.0
    second_ratio: float = 0.25
    residual_ratio: float = 0.12
    max_saturated: int = 2
    saturation_level: float | None = None  # default: full scale of the dtype
    centroid_threshold: float = 0.1
    max_aspect: float = 2.0
    min_quality: float = 0.2
    fit: bool = True
    speckle_weighting: bool = True
    max_iterations: int = 30


@dataclass(frozen=True)
class SpotDetection:
    """Result of :func:`detect_spot`: pixel centre ``(u, v)`` or ``ok=False`` with a reason."""

    ok: bool
    u: float = float("nan")
    v: float = float("nan")
    quality: float = 0.0
    reason: str = ""
    amplitude: float = 0.0
    background: float = 0.0
    sigma_major: float = float("nan")
    sigma_minor: float = float("nan")
    snr: float = 0.0
    fit_rms: float = float("nan")
    centroid: tuple[float, float] = (float("nan"), float("nan"))


def _reject(reason: str, **kw: Any) -> SpotDetection:
    return SpotDetection(False, reason=reason, **kw)


#: Reason of a detection refused because the camera delivered the previous image again.
FROZEN_FRAME = "frozen frame: the camera sent the same image twice (stalled stream or driver)"


class FrozenFrameCheck:
    """Detects a frozen camera: a frame bit-for-bit equal to the previous one.

    A live sensor's read noise makes two real frames differ; an identical frame means a stalled
    stream (a driver re-delivering its last buffer). Compares a BLAKE2b digest of the pixels,
    shape and dtype with the previous frame's.
    """

    def __init__(self) -> None:
        self._last: bytes | None = None

    def is_frozen(self, frame: np.ndarray) -> bool:
        """True when ``frame`` equals the previous frame given here; remembers ``frame``."""
        import hashlib

        h = hashlib.blake2b(np.ascontiguousarray(frame).data, digest_size=16)
        h.update(f"{frame.shape}{frame.dtype}".encode())
        digest = h.digest()
        frozen, self._last = digest == self._last, digest
        return frozen

    def detect(self, frame: np.ndarray, background: np.ndarray | None,
               config: DetectorConfig) -> SpotDetection:
        """:func:`detect_spot`, or a rejection with :data:`FROZEN_FRAME`."""
        if self.is_frozen(frame):
            return _reject(FROZEN_FRAME)
        return detect_spot(frame, background, config)


def _grey(frame: np.ndarray) -> np.ndarray:
    if frame.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(frame, code)
    if frame.ndim != 2:
        raise DriverError(f"camera frame has shape {frame.shape}; expected (H, W) or (H, W, 3)")
    return frame


def fit_gaussian_2d(patch: np.ndarray, u0: float, v0: float, sigma0: float,
                    max_iterations: int = 30, start: np.ndarray | None = None,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, float, bool]:
    """Least-squares fit of ``A exp(-(a du^2 + 2 b du dv + c dv^2) / 2) + B`` to ``patch``.

    ``du = col - u0'``, ``dv = row - v0'``; parameters ``p = (A, u0', v0', a, b, c, B)`` start
    from the given centre, an isotropic ``sigma0`` and the patch's extremes. Levenberg-Marquardt
    on the analytic Jacobian. Returns ``(p, rms_residual, converged)``.
    """
    h, w = patch.shape
    y = patch.astype(np.float64).ravel()
    uu = np.tile(np.arange(w, dtype=np.float64), h)
    vv = np.repeat(np.arange(h, dtype=np.float64), w)
    b0 = float(np.median(np.concatenate([patch[0], patch[-1], patch[:, 0], patch[:, -1]])))
    p = (np.array([float(y.max()) - b0, u0, v0, 1 / sigma0**2, 0.0, 1 / sigma0**2, b0])
         if start is None else np.asarray(start, dtype=np.float64).copy())
    sw = None if weights is None else np.sqrt(np.asarray(weights, dtype=np.float64).ravel())
    jt = np.empty((7, y.size))  # the Jacobian, transposed
    jt[6] = 1.0 if sw is None else sw

    def evaluate(p: np.ndarray) -> tuple[np.ndarray, float, tuple[np.ndarray, ...]]:
        du, dv = uu - p[1], vv - p[2]
        uu2, uv2, vv2 = du * du, du * dv, dv * dv
        g = np.exp(-0.5 * (p[3] * uu2 + 2 * p[4] * uv2 + p[5] * vv2))
        r = y - (p[0] * g + p[6])
        if sw is not None:
            r *= sw
        return r, float(r @ r), (g, du, dv, uu2, uv2, vv2)

    def fill_jacobian(p: np.ndarray, parts: tuple[np.ndarray, ...]) -> None:
        g, du, dv, uu2, uv2, vv2 = parts
        ag = p[0] * g if sw is None else p[0] * g * sw
        jt[0] = g if sw is None else g * sw
        jt[1] = ag * (p[3] * du + p[4] * dv)
        jt[2] = ag * (p[4] * du + p[5] * dv)
        jt[3] = -0.5 * ag * uu2
        jt[4] = -ag * uv2
        jt[5] = -0.5 * ag * vv2

    r, cost, parts = evaluate(p)
    lam = 1e-3
    converged = False
    for _ in range(max_iterations):
        fill_jacobian(p, parts)
        jtj, jtr = jt @ jt.T, jt @ r
        diag = np.diag(np.diag(jtj))
        improved = False
        for _ in range(8):
            try:
                step = np.linalg.solve(jtj + lam * diag, jtr)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            trial = p + step
            if trial[3] <= 0 or trial[5] <= 0 or trial[3] * trial[5] <= trial[4] ** 2:
                lam *= 10
                continue
            r_t, cost_t, parts_t = evaluate(trial)
            if cost_t <= cost:
                rel = (cost - cost_t) / max(cost, 1e-300)
                p, r, cost, parts = trial, r_t, cost_t, parts_t
                lam = max(lam / 10, 1e-9)
                improved = True
                converged = rel < 1e-9 or max(abs(step[1]), abs(step[2])) < 1e-4
                break
            lam *= 10
        if not improved or converged:
            converged = converged or not improved
            break
    return p, math.sqrt(cost / y.size), converged


def _speckle_refit(patch: np.ndarray, p: np.ndarray, read_noise: float,
                   max_iterations: int) -> tuple[np.ndarray, float]:
    """Refit with weights ``1 / (s_n^2 + k^2 m^2)`` when speckle (noise growing with the model
    ``m``) dominates: ``k^2`` is the least-squares slope of ``r^2 - s_n^2`` on ``m^2``."""
    h, w = patch.shape
    vv, uu = np.mgrid[0:h, 0:w]
    du, dv = uu - p[1], vv - p[2]
    m = p[0] * np.exp(-0.5 * (p[3] * du * du + 2 * p[4] * du * dv + p[5] * dv * dv))
    res = patch - m - p[6]
    rms = math.sqrt(float(np.mean(res * res)))
    s2 = read_noise**2
    m2 = m * m
    k2 = float(np.sum((res * res - s2) * m2) / max(float(np.sum(m2 * m2)), 1e-300))
    if k2 * float(m2.max()) < 4.0 * s2:  # speckle < 2x read noise at the peak: keep the fit
        return p, rms
    p2, _, _ = fit_gaussian_2d(patch, p[1], p[2], 1.0, max_iterations, start=p,
                               weights=1.0 / (s2 + k2 * m2))
    if not (p2[0] > 0 and abs(p2[1] - p[1]) < 1.0 and abs(p2[2] - p[2]) < 1.0):
        return p, rms
    du, dv = uu - p2[1], vv - p2[2]
    m = p2[0] * np.exp(-0.5 * (p2[3] * du * du + 2 * p2[4] * du * dv + p2[5] * dv * dv))
    return p2, math.sqrt(float(np.mean((patch - m - p2[6]) ** 2)))


def _gauss(p: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``A exp(-(a du^2 + 2 b du dv + c dv^2) / 2)`` (no background) over a patch grid."""
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    du, dv = uu - p[1], vv - p[2]
    return p[0] * np.exp(-0.5 * (p[3] * du * du + 2 * p[4] * du * dv + p[5] * dv * dv))


def detect_spot(frame: np.ndarray, background: np.ndarray | None = None,
                config: DetectorConfig | None = None) -> SpotDetection:
    """Find the laser spot in a grey frame to sub-pixel accuracy (see the module docstring)."""
    cfg = config or DetectorConfig()
    img = _grey(frame)
    full_scale = (cfg.saturation_level if cfg.saturation_level is not None
                  else float(np.iinfo(img.dtype).max) if img.dtype.kind in "ui" else 1.0)
    if background is not None:
        bg = _grey(background)
        if bg.shape != img.shape:
            raise DriverError(f"background frame {bg.shape} does not match the frame "
                              f"{img.shape}; capture the background again")
        diff = cv2.subtract(img, bg) if img.dtype == bg.dtype and img.dtype.kind == "u" \
            else np.clip(img.astype(np.float32) - bg.astype(np.float32), 0, None)
    else:
        bg, diff = None, img
    h, w = img.shape
    k = max(1, int(cfg.coarse))
    small = cv2.resize(diff, (w // k, h // k), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    _, peak, _, (cu, cv_) = cv2.minMaxLoc(small)
    sample = small[::4, ::4]
    floor = float(np.median(sample))
    noise = 1.4826 * float(np.median(np.abs(sample - floor)))
    height = peak - floor
    if height < cfg.min_contrast or height < cfg.min_snr * noise:
        return _reject(f"no spot: brightest region only {height:.1f} grey levels above the "
                       f"background (need {max(cfg.min_contrast, cfg.min_snr * noise):.1f})")

    # ROI centred on the brightest (3 x 3 mean) pixel around the coarse sample
    r0, c0 = max(0, (cv_ - 1) * k), max(0, (cu - 1) * k)
    cell = cv2.blur(diff[r0:(cv_ + 2) * k, c0:(cu + 2) * k], (3, 3))
    dv, du = np.unravel_index(int(np.argmax(cell)), cell.shape)
    pu, pv = c0 + int(du), r0 + int(dv)
    rh = cfg.roi_half
    if pu - rh < 0 or pv - rh < 0 or pu + rh >= w or pv + rh >= h:
        return _reject(f"spot at the image border (pixel {pu}, {pv}); move it into the view")
    sl = (slice(pv - rh, pv + rh + 1), slice(pu - rh, pu + rh + 1))
    n_sat = int(np.count_nonzero(img[sl] >= full_scale))
    if n_sat > cfg.max_saturated:
        return _reject(f"saturated: {n_sat} pixels at full scale; lower the exposure or gain")
    patch = img[sl].astype(np.float32)
    if bg is not None:
        patch -= bg[sl].astype(np.float32)

    # intensity-weighted centroid over the local background
    border = np.concatenate([patch[0], patch[-1], patch[1:-1, 0], patch[1:-1, -1]])
    b0 = float(np.median(border))
    # border noise, at least the quantisation noise of one grey level (1 / sqrt(12))
    b_noise = max(1.4826 * float(np.median(np.abs(border - b0))), 0.2887)
    wgt = patch - b0
    amp = float(wgt.max())
    wgt = np.where(wgt > cfg.centroid_threshold * amp, wgt, 0.0)
    total = float(wgt.sum())
    vv, uu = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
    cu_ = float((wgt * uu).sum() / total)
    cv2_ = float((wgt * vv).sum() / total)
    var = float((wgt * ((uu - cu_) ** 2 + (vv - cv2_) ** 2)).sum() / total) / 2
    # a Gaussian cut at a fraction f of its peak keeps a fraction c = 1 - T f / (1 - f),
    # T = ln(1 / f), of its second moment
    f_cut = min(max(cfg.centroid_threshold, 1e-6), 0.9)
    t_cut = -math.log(f_cut)
    c_cut = 1.0 - t_cut * f_cut / (1.0 - f_cut)
    sigma0 = max(0.7, math.sqrt(max(var / c_cut, 0.25)))
    centroid = (pu - rh + cu_, pv - rh + cv2_)

    if cfg.fit:
        # fit window: +-4 sigma around the centroid, inside the ROI
        fw = max(5, math.ceil(4.0 * sigma0))
        i0, j0 = round(cv2_), round(cu_)
        v0, v1 = max(0, i0 - fw), min(patch.shape[0], i0 + fw + 1)
        u0, u1 = max(0, j0 - fw), min(patch.shape[1], j0 + fw + 1)
        sub = patch[v0:v1, u0:u1]
        p, _, _ = fit_gaussian_2d(sub, cu_ - u0, cv2_ - v0, sigma0, cfg.max_iterations)
        if cfg.speckle_weighting and p[0] > 0:
            p, _ = _speckle_refit(sub, p, b_noise, cfg.max_iterations)
        p[1] += u0
        p[2] += v0
        if not (p[0] > 0 and 0 <= p[1] <= 2 * rh and 0 <= p[2] <= 2 * rh):
            return _reject("ambiguous spot: the Gaussian fit did not converge inside the ROI",
                           centroid=centroid)
        eig = np.linalg.eigvalsh(np.array([[p[3], p[4]], [p[4], p[5]]]))
        s_major, s_minor = 1 / math.sqrt(eig[0]), 1 / math.sqrt(eig[1])
        u_roi, v_roi, a_fit, b_fit = float(p[1]), float(p[2]), float(p[0]), float(p[6])
        resid = patch - b_fit - _gauss(p, patch.shape)
    else:
        s_major = s_minor = sigma0
        u_roi, v_roi, a_fit, b_fit = cu_, cv2_, amp, b0
        iso = np.array([amp, cu_, cv2_, 1 / sigma0**2, 0.0, 1 / sigma0**2])
        resid = patch - b0 - _gauss(iso, patch.shape)

    # quality: SNR and the misfit beyond the read noise, over the whole ROI
    rms = math.sqrt(float(np.mean(resid * resid)))
    misfit = math.sqrt(max(rms * rms - b_noise * b_noise, 0.0)) / a_fit
    snr = a_fit / b_noise
    quality = snr / (snr + 10.0) * math.exp(-((misfit / 0.05) ** 2))
    common = dict(quality=quality, amplitude=a_fit, background=b_fit, sigma_major=s_major,
                  sigma_minor=s_minor, snr=snr, fit_rms=rms, centroid=centroid)
    if s_minor < 0.5:
        return _reject(f"not a laser spot: width {s_minor:.2f} px (a hot pixel?)", **common)
    if s_major > rh / 2.5:
        return _reject(f"spot too wide for the ROI (sigma {s_major:.1f} px > "
                       f"{rh / 2.5:.1f}): two spots, or raise roi_half", **common)
    # a second spot inside the ROI shows as a residual blob; outside it, on the coarse image
    blob = float(cv2.blur(resid, (3, 3)).max())
    if blob > cfg.residual_ratio * a_fit + 3.0 * b_noise:
        return _reject(f"two spots: a second peak at {100 * blob / a_fit:.0f}% of the first "
                       "next to it (a reflection?)", **common)
    rad = math.ceil((3.5 * s_major + 1.0) / k)
    cvi, cui = round((pv - rh + v_roi) / k), round((pu - rh + u_roi) / k)
    masked = small.copy()
    masked[max(0, cvi - rad):cvi + rad + 1, max(0, cui - rad):cui + rad + 1] = floor
    _, second, _, (su, sv) = cv2.minMaxLoc(masked)
    if second - floor > cfg.second_ratio * height and second - floor > cfg.min_contrast / 2:
        return _reject(f"two spots: a second one near pixel ({su * k + k // 2}, "
                       f"{sv * k + k // 2}) at {100 * (second - floor) / height:.0f}% "
                       "of the first", **common)
    if s_major / s_minor > cfg.max_aspect:
        return _reject(f"elongated spot (axes {s_major:.1f} x {s_minor:.1f} px): two "
                       "overlapping spots or a reflection?", **common)
    if quality < cfg.min_quality:
        return _reject(f"ambiguous spot shape (quality {quality:.2f}): two overlapping spots "
                       "or a reflection?", **common)
    return SpotDetection(True, pu - rh + u_roi, pv - rh + v_roi, **common)


# -- pixel -> plate mapping -------------------------------------------------------------------

@dataclass(frozen=True)
class PixelToPlate:
    """Pixel ``(u, v)`` -> plate ``(x, y)`` mm: ``cv2.undistortPoints`` (``P = K``) then ``H``.

    ``camera_matrix`` K and ``dist_coeffs`` (OpenCV order); ``homography`` maps undistorted
    pixels to the fixed frame; ``rms_px`` is the chessboard reprojection RMS that produced it.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    homography: np.ndarray
    rms_px: float = float("nan")
    rms_mm: float = float("nan")
    n_corners: int = 0
    extra: Mapping[str, float] = field(default_factory=dict)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (n, 2) -> ideal pixels (n, 2)."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        k = self.camera_matrix
        return cv2.undistortPoints(pts, k, self.dist_coeffs, P=k).reshape(-1, 2)

    def to_plate(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) -> plate mm (n, 2)."""
        ideal = self.undistort(uv).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(ideal, self.homography).reshape(-1, 2)

    def mm_per_px(self, uv: np.ndarray) -> float:
        """Local scale at ``uv`` (mm per pixel, geometric mean of the two axes)."""
        p = np.asarray(uv, dtype=float).reshape(1, 2)
        x = self.to_plate(np.vstack([p, p + np.array([1.0, 0.0]), p + np.array([0.0, 1.0])]))
        return math.sqrt(float(np.linalg.norm(x[1] - x[0]) * np.linalg.norm(x[2] - x[0])))

    def to_json_dict(self) -> dict[str, Any]:
        return {"camera_matrix": self.camera_matrix.tolist(),
                "dist_coeffs": np.ravel(self.dist_coeffs).tolist(),
                "homography": self.homography.tolist(), "rms_px": self.rms_px,
                "rms_mm": self.rms_mm, "n_corners": self.n_corners}

    @classmethod
    def from_json_dict(cls, d: Mapping[str, Any]) -> PixelToPlate:
        try:
            k = np.asarray(d["camera_matrix"], dtype=float)
            dist = np.asarray(d["dist_coeffs"], dtype=float)
            hom = np.asarray(d["homography"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise DriverError(f"camera calibration file is incomplete or malformed ({exc})") \
                from None
        if k.shape != (3, 3) or hom.shape != (3, 3) or dist.size not in (4, 5, 8, 12, 14):
            raise DriverError("camera calibration file: camera_matrix and homography must be "
                              "3x3 and dist_coeffs 4, 5, 8, 12 or 14 numbers")
        return cls(k, dist, hom, float(d.get("rms_px", "nan")), float(d.get("rms_mm", "nan")),
                   int(d.get("n_corners", 0)))


def find_chessboard(image: np.ndarray, pattern: tuple[int, int],
                    refine: bool = True) -> np.ndarray:
    """Inner corners (cols * rows, 2) px of a chessboard, row by row, first corner nearest the
    image's top-left (``cv2.findChessboardCornersSB``, then ``cv2.cornerSubPix``)."""
    grey = _grey(image)
    if grey.dtype != np.uint8:
        grey = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    ok, corners = cv2.findChessboardCornersSB(grey, pattern, flags=0)
    if not ok:
        raise DriverError(f"chessboard with {pattern[0]}x{pattern[1]} inner corners not found; "
                          "check the pattern size, focus and lighting")
    corners = corners.reshape(-1, 1, 2).astype(np.float32)
    if refine:
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
        corners = cv2.cornerSubPix(grey, corners, (7, 7), (-1, -1), crit)
    c = corners.reshape(-1, 2).astype(np.float64)
    if c[0].sum() > c[-1].sum():  # resolve the 180 degree ambiguity of the corner order
        c = c[::-1].copy()
    return c


def calibrate_chessboard(image: np.ndarray, pattern: tuple[int, int], corners_mm: np.ndarray,
                         camera_matrix: np.ndarray | None = None,
                         dist_coeffs: np.ndarray | None = None,
                         estimate_distortion: bool = False) -> PixelToPlate:
    """Fit the pixel -> plate mapping from one image of a chessboard lying on the plate.

    ``corners_mm`` (cols * rows, 2): the fixed-frame positions of the inner corners in the
    order of :func:`find_chessboard` (row by row from the corner nearest the image's top-left).
    Intrinsics: given (a prior lens calibration), or with ``estimate_distortion`` a one-view
    ``cv2.calibrateCamera`` with fixed principal point and aspect ratio and only k1, k2 free;
    else a distortion-free pinhole. Then ``H = cv2.findHomography(undistorted, corners_mm)``.
    """
    corners = find_chessboard(image, pattern)
    obj = np.asarray(corners_mm, dtype=np.float64).reshape(-1, 2)
    if obj.shape[0] != corners.shape[0]:
        raise DriverError(f"chessboard: {corners.shape[0]} corners found but "
                          f"{obj.shape[0]} plate positions given")
    h, w = _grey(image).shape
    if camera_matrix is None:
        f = float(max(w, h))
        camera_matrix = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    k = np.asarray(camera_matrix, dtype=np.float64)
    dist = np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64)
    if estimate_distortion:
        obj3 = np.column_stack([obj - obj.mean(axis=0), np.zeros(len(obj))]).astype(np.float32)
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT
                 | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3)
        _, k, dist, _, _ = cv2.calibrateCamera([obj3], [corners.astype(np.float32)], (w, h),
                                               k.copy(), dist.copy(), flags=flags)
    mapping = PixelToPlate(k, np.ravel(dist), np.eye(3))
    ideal = mapping.undistort(corners)
    hom, _ = cv2.findHomography(ideal, obj, 0)
    if hom is None:
        raise DriverError("chessboard: homography fit failed (degenerate corner layout)")
    mapped = cv2.perspectiveTransform(ideal.reshape(-1, 1, 2), hom).reshape(-1, 2)
    rms_mm = float(np.sqrt(np.mean(np.sum((mapped - obj) ** 2, axis=1))))
    back = cv2.perspectiveTransform(obj.reshape(-1, 1, 2), np.linalg.inv(hom)).reshape(-1, 2)
    rms_px = float(np.sqrt(np.mean(np.sum((back - ideal) ** 2, axis=1))))
    return PixelToPlate(k, np.ravel(dist), hom, rms_px, rms_mm, len(obj))


def measurement_from(det: SpotDetection, mapping: PixelToPlate | None) -> SpotMeasurement:
    """A :class:`SpotMeasurement` from a detection, with plate mm when ``mapping`` is set."""
    extra = {"snr": det.snr, "amplitude": det.amplitude, "sigma_major": det.sigma_major,
             "sigma_minor": det.sigma_minor}
    if not det.ok:
        return SpotMeasurement(False, quality=det.quality, reason=det.reason, extra=extra)
    if mapping is None:
        return SpotMeasurement(False, u=det.u, v=det.v, quality=det.quality,
                               reason="camera not calibrated: run the chessboard calibration",
                               extra=extra)
    x, y = mapping.to_plate(np.array([[det.u, det.v]]))[0]
    return SpotMeasurement(True, float(x), float(y), det.u, det.v, det.quality, extra=extra)


class OpenCVCamera:
    """A camera through ``cv2.VideoCapture`` (device index, URL, or an image sequence pattern
    such as ``frames/%03d.png``) implementing :class:`drivers.base.SpotCamera`."""

    def __init__(self, source: int | str, mapping: PixelToPlate | None = None,
                 config: DetectorConfig | None = None, average: int = 1) -> None:
        self.source = source
        self.mapping = mapping
        self.config = config or DetectorConfig()
        self.average = max(1, int(average))
        self.background: np.ndarray | None = None
        self._frozen = FrozenFrameCheck()
        self._cap = cv2.VideoCapture(source)
        if not self._cap.isOpened():
            raise DriverError(f"camera {source!r} cannot be opened; check the index or URL")

    def grab(self) -> np.ndarray:
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise DriverError(f"camera {self.source!r} returned no frame")
        return _grey(frame)

    def capture_background(self, n: int = 5) -> np.ndarray:
        """Median of ``n`` frames taken with the laser off; used for background subtraction."""
        frames = np.stack([self.grab() for _ in range(max(1, n))])
        self.background = np.median(frames, axis=0).astype(frames.dtype)
        return self.background

    def calibrate(self, pattern: tuple[int, int], corners_mm: np.ndarray,
                  camera_matrix: np.ndarray | None = None,
                  dist_coeffs: np.ndarray | None = None,
                  estimate_distortion: bool = False) -> PixelToPlate:
        """Chessboard step: grab a frame of the board on the plate and fit the mapping."""
        self.mapping = calibrate_chessboard(self.grab(), pattern, corners_mm, camera_matrix,
                                            dist_coeffs, estimate_distortion)
        return self.mapping

    def detect(self) -> SpotDetection:
        """Grab and detect; a frame identical to the previous one is refused (frozen)."""
        return self._frozen.detect(self.grab(), self.background, self.config)

    def measure_spot(self) -> SpotMeasurement:
        return measure_average(self.detect, self.mapping, self.average)

    def close(self) -> None:
        self._cap.release()


def measure_average(detect: Any, mapping: PixelToPlate | None, n: int) -> SpotMeasurement:
    """Detect ``n`` times and average the good detections' pixels (quality: their mean)."""
    dets = [detect() for _ in range(max(1, n))]
    good = [d for d in dets if d.ok]
    if not good:
        return measurement_from(dets[-1], mapping)
    if len(good) == 1:
        return measurement_from(good[0], mapping)
    mean = SpotDetection(True, float(np.mean([d.u for d in good])),
                         float(np.mean([d.v for d in good])),
                         float(np.mean([d.quality for d in good])),
                         amplitude=float(np.mean([d.amplitude for d in good])),
                         sigma_major=float(np.mean([d.sigma_major for d in good])),
                         sigma_minor=float(np.mean([d.sigma_minor for d in good])),
                         snr=float(np.mean([d.snr for d in good])))
    return measurement_from(mean, mapping)
