"""API benchmark: GET /status latency under 50 concurrent clients.

Starts the whole system on simulated hardware (the launcher, loopback only), then 50
asyncio clients (httpx, one connection each) ask ``/status`` back to back for
``--seconds``; prints requests/s and the latency p50/p90/p99/max, and the same for
``/runs`` (SQLite) as a second line. Bounded in count (``--clients``) and time.

    ./dev bench api            # or: python bench/api.py --clients 50 --seconds 10
"""

from __future__ import annotations

import argparse
import asyncio
import os
import time
from pathlib import Path

import httpx
import numpy as np

from semservo import jsontext
from semservo.config import Settings
from semservo.launcher import Launcher

OUT = Path(__file__).parent / "results"


async def hammer(url: str, path: str, clients: int, seconds: float) -> dict:
    latencies: list[float] = []
    errors = 0
    deadline = time.monotonic() + seconds

    async def one_client() -> None:
        nonlocal errors
        async with httpx.AsyncClient(base_url=url, timeout=10) as http:
            while time.monotonic() < deadline:
                started = time.perf_counter()
                response = await http.get(path)
                latencies.append((time.perf_counter() - started) * 1000)
                errors += response.status_code != 200

    started = time.monotonic()
    await asyncio.gather(*(one_client() for _ in range(clients)))
    elapsed = time.monotonic() - started
    values = np.array(latencies)
    return {"path": path, "clients": clients, "requests": len(values), "errors": errors,
            "requests_per_s": len(values) / elapsed,
            **{f"p{q}_ms": float(np.percentile(values, q)) for q in (50, 90, 99)}, "max_ms": float(values.max())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clients", type=int, default=50, help="concurrent clients (default 50)")
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds per endpoint (default 10)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if not 1 <= args.clients <= 500 or not 0 < args.seconds <= 120:
        parser.error("clients must be 1..500 and seconds 0..120 (the benchmark is bounded)")
    os.environ.setdefault("SEMSERVO_GATEWAY__DATABASE", str(args.out / "api-bench.sqlite"))
    settings = Settings()
    args.out.mkdir(parents=True, exist_ok=True)
    log = (args.out / "api-services.log").open("w")
    launcher = Launcher(settings, out=log)
    launcher.start(timeout_s=120)
    url = f"http://127.0.0.1:{settings.gateway.http_port}"
    try:
        time.sleep(1.0)
        results = [asyncio.run(hammer(url, path, args.clients, args.seconds)) for path in ("/status", "/runs")]
    finally:
        launcher.stop()
        log.close()
    print(f"{'endpoint':<10} {'clients':>7} {'requests':>9} {'req/s':>8} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} "
          f"{'max ms':>8} errors")
    for r in results:
        print(f"{r['path']:<10} {r['clients']:>7} {r['requests']:>9} {r['requests_per_s']:>8.0f} {r['p50_ms']:>8.1f} "
              f"{r['p90_ms']:>8.1f} {r['p99_ms']:>8.1f} {r['max_ms']:>8.1f} {r['errors']}")
    (args.out / "api.json").write_text(jsontext.dumps(results, indent=1))
    print(f"wrote {args.out / 'api.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
