"""Dashboard figures: live-spot updates/s delivered to websocket clients, and Solve H latency.

Run: ``/work/venv/bin/python bench/bench_dashboard.py [--seconds 5] [--clients 1,10]``.

1. Live view: the simulated cell with the live view on; N websocket clients connect through
   the token guard (as a browser does) and count the ``/cell/live_spot`` position updates they
   receive (viser wire format: zstd-compressed msgpack).
2. Solve H: a 42-pose simulated acquisition, then in headless Chromium the time from the
   click on **Solve H** to the results table of that solve shown in the page (JS clock), and
   the server-side time from the click event to the panels updated.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from pathlib import Path

import msgspec.msgpack
import viser
import websockets
import zstandard

from app.panels import build_dashboard
from app.server import GuardedServer
from drivers.sim.workcell import load_workcell

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]


def count_spot_updates(frame: bytes, dctx: zstandard.ZstdDecompressor) -> int:
    """Live-spot position messages in one viser websocket frame."""
    size = int.from_bytes(frame[0:8], "little")
    csize = int.from_bytes(frame[8:16], "little")
    payload = msgspec.msgpack.decode(dctx.decompress(frame[16:16 + csize], max_output_size=size))
    return sum(1 for m in payload["messages"]
               if m.get("name") == "/cell/live_spot" and "Position" in m.get("type", ""))


async def _client(url: str, origin: str, seconds: float) -> float:
    dctx = zstandard.ZstdDecompressor()
    n = 0
    async with websockets.connect(url, subprotocols=[f"viser-v{viser.__version__}"],
                                  additional_headers={"Origin": origin}, max_size=None) as ws:
        t_end = time.monotonic() + seconds
        t0 = time.monotonic()
        while time.monotonic() < t_end:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=t_end - time.monotonic())
            except TimeoutError:
                break
            if isinstance(frame, bytes) and time.monotonic() - t0 > 0.5:  # skip the backlog
                n += count_spot_updates(frame, dctx)
        return n / (seconds - 0.5)


def bench_live(seconds: float, clients: list[int]) -> None:
    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    app = build_dashboard(server.viser, load_workcell(None))
    try:
        time.sleep(1.0)
        url = f"ws://127.0.0.1:{guard.port}/?token={guard.token}"
        origin = f"http://127.0.0.1:{guard.port}"
        for n in clients:
            async def run(n: int = n) -> list[float]:
                return await asyncio.gather(*[_client(url, origin, seconds) for _ in range(n)])
            n0 = app.scene.pose_updates
            t0 = time.monotonic()
            rates = asyncio.run(run())
            produced = (app.scene.pose_updates - n0) / (time.monotonic() - t0)
            print(f"live view, {n:2d} client(s): spot updates received per client "
                  f"min {min(rates):.1f} / median {statistics.median(rates):.1f} Hz "
                  f"(server produced {produced:.1f} Hz)")
    finally:
        app.worker.stop()
        server.stop()


def rss_mb() -> float:
    """Resident set size of this process (MB), from /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_soak(seconds: float, clients: int) -> None:
    """Live view with ``clients`` connected for ``seconds``: RSS every 10 % of the run."""
    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    app = build_dashboard(server.viser, load_workcell(None))
    url = f"ws://127.0.0.1:{guard.port}/?token={guard.token}"
    origin = f"http://127.0.0.1:{guard.port}"
    samples: list[tuple[float, float]] = []
    stop = False

    def sample() -> None:
        t0 = time.monotonic()
        while not stop:
            samples.append((time.monotonic() - t0, rss_mb()))
            time.sleep(max(seconds / 10, 0.5))
    import threading
    sampler = threading.Thread(target=sample, daemon=True)
    try:
        time.sleep(1.0)
        sampler.start()

        async def run() -> list[float]:
            return await asyncio.gather(*[_client(url, origin, seconds) for _ in range(clients)])
        rates = asyncio.run(run())
    finally:
        stop = True
        app.worker.stop()
        server.stop()
    first, last = samples[1][1], samples[-1][1]
    print(f"soak {seconds:.0f} s, {clients} client(s): live {min(rates):.1f} Hz min per client;"
          f" RSS {first:.1f} MB -> {last:.1f} MB ({last - first:+.1f} MB); samples "
          + ", ".join(f"{t:.0f}s:{m:.0f}" for t, m in samples))


def bench_solve(repeats: int) -> None:
    from playwright.sync_api import sync_playwright

    workdir = Path(tempfile.mkdtemp(prefix="bench-dashboard-"))
    server = GuardedServer("127.0.0.1", 0)
    guard = server.start()
    app = build_dashboard(server.viser, load_workcell(None), session_path=workdir / "s.db")
    try:
        from app.panels import acquire
        app.worker.call("acquire", lambda: acquire.run_acquisition(app, 1), 120)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.set_default_timeout(60_000)
            page.goto(guard.url)
            page.get_by_role("tab", name="Solve").click()
            page.get_by_role("button", name="Solve H").wait_for()
            shown, server_side = [], []
            for k in range(1, repeats + 1):
                ms = page.evaluate("""(k) => new Promise((resolve) => {
                    const btn = [...document.querySelectorAll('button')]
                        .find((b) => b.textContent.trim() === 'Solve H');
                    const t0 = performance.now();
                    const done = () => document.body.innerText.includes('Solve #' + k + ':')
                        && document.querySelector('table') !== null;
                    const obs = new MutationObserver(() => {
                        if (done()) { obs.disconnect(); resolve(performance.now() - t0); }
                    });
                    obs.observe(document.body, {childList: true, subtree: true,
                                                characterData: true});
                    btn.click();
                })""", k)
                shown.append(ms / 1000)
                server_side.append(app.last_solve_s or float("nan"))
            browser.close()
        n = app.solve_view.calibration.n_points
        print(f"Solve H ({n} poses): click -> results shown in Chromium: first "
              f"{shown[0]:.3f} s, median {statistics.median(shown):.3f} s, max {max(shown):.3f} s"
              f" over {repeats}; server click-event -> panels updated median "
              f"{statistics.median(server_side):.3f} s")
    finally:
        app.worker.stop()
        app.close_session()
        server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--clients", default="1,10", help="comma-separated client counts")
    parser.add_argument("--repeats", type=int, default=5, help="Solve H clicks to time")
    parser.add_argument("--soak", type=float, default=0.0, metavar="SECONDS",
                        help="only run a live-view soak this long and report the memory")
    args = parser.parse_args()
    if args.soak:
        bench_soak(args.soak, max(int(c) for c in args.clients.split(",")))
        return
    bench_live(args.seconds, [int(c) for c in args.clients.split(",")])
    bench_solve(args.repeats)


if __name__ == "__main__":
    main()
