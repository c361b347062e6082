"""Soak: 10 dashboard clients during a live acquisition; live-view rate and memory over time.

Run: ``/work/venv/bin/python bench/bench_soak.py [--seconds 1800] [--clients 10] [--json]``.

The simulated cell acquires the seed's 42-pose grid again and again (each run into a new
session file in a temporary directory, as an operator calibrating repeatedly would), while
``--clients`` websocket clients connect through the token guard as browsers do and count the
live-view updates they receive (viser wire format): position messages of the live spot and
of the flange. Client 0 is the operator. The
resident set size of the server process is sampled every 5 % of the run; growth is measured
from the end of the warm-up (the first quarter, when caches and the first sessions fill) to
the end.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec.msgpack
import viser
import websockets
import zstandard

try:  # run as a script (bench/ on sys.path) or imported as bench.bench_soak
    from bench_dashboard import rss_mb
except ImportError:  # pragma: no cover - import path depends on how it is started
    from bench.bench_dashboard import rss_mb

#: Scene nodes whose position messages make the live view: the live spot and the flange.
LIVE_NODES = ("/cell/live_spot", "/cell/flange")


async def _client(url: str, origin: str, seconds: float) -> dict[str, float]:
    """Position updates per second received for each of :data:`LIVE_NODES` (after 0.5 s)."""
    dctx = zstandard.ZstdDecompressor()
    counts = dict.fromkeys(LIVE_NODES, 0)
    async with websockets.connect(url, subprotocols=[f"viser-v{viser.__version__}"],
                                  additional_headers={"Origin": origin}, max_size=None) as ws:
        t0 = time.monotonic()
        t_end = t0 + seconds
        while time.monotonic() < t_end:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=t_end - time.monotonic())
            except TimeoutError:
                break
            if not isinstance(frame, bytes) or time.monotonic() - t0 < 0.5:  # the backlog
                continue
            size = int.from_bytes(frame[0:8], "little")
            csize = int.from_bytes(frame[8:16], "little")
            payload = msgspec.msgpack.decode(dctx.decompress(frame[16:16 + csize],
                                                             max_output_size=size))
            for m in payload["messages"]:
                if m.get("name") in counts and "Position" in m.get("type", ""):
                    counts[m["name"]] += 1
    return {name: n / (seconds - 0.5) for name, n in counts.items()}


def soak(seconds: float, clients: int = 10, move_time: float | None = None) -> dict[str, object]:
    """Run the soak; returns the figures (rates Hz, RSS MB, poses and sessions stored).

    ``move_time`` (s) overrides the simulated robot's move duration (None: the dashboard's).
    """
    from app.panels import acquire, build_dashboard
    from app.server import GuardedServer
    from drivers.sim.workcell import load_workcell

    workdir = Path(tempfile.mkdtemp(prefix="lasercal-soak-"))
    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    app = build_dashboard(server.viser, load_workcell(None), session_path=workdir / "run-0.db")
    stop = threading.Event()
    rss: list[tuple[float, float]] = []
    runs: list[tuple[str, int]] = []
    errors: list[str] = []

    def acquisitions() -> None:
        k = 0
        while not stop.is_set():
            path = workdir / f"run-{k}.db"

            def fresh(path: Path = path) -> None:
                app.close_session()
                app.runner, app.session_path = None, path
            try:
                app.worker.call("new session", fresh, 30)
                progress = app.worker.call("acquire", lambda: acquire.run_acquisition(app, 3),
                                           600)
            except Exception as exc:  # reported in the figures, the soak goes on
                errors.append(f"{type(exc).__name__}: {exc}")
                time.sleep(0.5)
                continue
            runs.append((progress.state, progress.done))
            k += 1

    def sampler() -> None:
        t0 = time.monotonic()
        while not stop.wait(max(seconds / 20, 0.5)):
            rss.append((time.monotonic() - t0, rss_mb()))

    try:
        deadline = time.monotonic() + 30
        while not app.connected and time.monotonic() < deadline:
            time.sleep(0.05)
        if move_time is not None:
            app.sim_move_time_s = move_time
            app.worker.call("reconnect", app.connect_sim, 30)
        threads = [threading.Thread(target=acquisitions, daemon=True),
                   threading.Thread(target=sampler, daemon=True)]
        rss.append((0.0, rss_mb()))
        for t in threads:
            t.start()
        url = f"ws://127.0.0.1:{guard.port}/?token={guard.token}"
        origin = f"http://127.0.0.1:{guard.port}"

        async def run() -> list[dict[str, float]]:
            return await asyncio.gather(*[_client(url, origin, seconds) for _ in range(clients)])
        per_client = asyncio.run(run())
        stop.set()
        app.runner.abort() if app.runner is not None else None
        for t in threads:
            t.join(30)
    finally:
        stop.set()
        app.worker.stop(timeout=10)
        app.close_session()
        server.stop()
    rss.append((seconds, rss_mb()))
    warm = [m for t, m in rss if t >= seconds / 4]
    spot = [c["/cell/live_spot"] for c in per_client]
    flange = [c["/cell/flange"] for c in per_client]
    return {
        "seconds": seconds, "clients": clients, "move_time_s": move_time,
        "operator_spot_hz": spot[0], "min_client_spot_hz": min(spot),
        "median_client_spot_hz": statistics.median(spot),
        "operator_flange_hz": flange[0], "min_client_flange_hz": min(flange),
        "rss_start_mb": rss[0][1], "rss_warm_mb": warm[0], "rss_end_mb": rss[-1][1],
        "rss_max_mb": max(m for _, m in rss),
        "rss_growth_after_warmup_mb": rss[-1][1] - warm[0],
        "rss_samples": [(round(t, 1), round(m, 1)) for t, m in rss],
        "acquisitions_finished": sum(1 for s, _ in runs if s == "finished"),
        "poses_stored": sum(n for _, n in runs), "errors": errors,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1800.0,
                        help="soak duration (default 1800 s = 30 min)")
    parser.add_argument("--clients", type=int, default=10, help="websocket clients (default 10)")
    parser.add_argument("--move-time", type=float, default=None, metavar="S",
                        help="simulated move duration (default: the dashboard's, 0.05 s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args()
    figures = soak(args.seconds, args.clients, args.move_time)
    if args.json:
        print(json.dumps(figures))
        return
    f = figures
    print(f"soak {f['seconds']:.0f} s, {f['clients']} clients, live acquisition, move time "
          f"{f['move_time_s'] if f['move_time_s'] is not None else 'default'} "
          f"({f['acquisitions_finished']} x 42-pose runs, {f['poses_stored']} poses stored):")
    print(f"  live spot position updates: operator {f['operator_spot_hz']:.1f} Hz, min client "
          f"{f['min_client_spot_hz']:.1f} Hz, median {f['median_client_spot_hz']:.1f} Hz")
    print(f"  flange position updates: operator {f['operator_flange_hz']:.1f} Hz, min client "
          f"{f['min_client_flange_hz']:.1f} Hz")
    print(f"  RSS: start {f['rss_start_mb']:.1f} MB, after warm-up {f['rss_warm_mb']:.1f} MB, "
          f"end {f['rss_end_mb']:.1f} MB (growth after warm-up "
          f"{f['rss_growth_after_warmup_mb']:+.1f} MB), max {f['rss_max_mb']:.1f} MB")
    print("  samples " + ", ".join(f"{t:.0f}s:{m:.0f}" for t, m in f["rss_samples"]))
    if f["errors"]:
        print(f"  errors: {f['errors']}", file=sys.stderr)


if __name__ == "__main__":
    main()
