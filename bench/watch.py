"""Watched-folder benchmark: from a frame's file being complete to the frame being
available to publish, through the image server's ``watch`` source.

A writer saves 512 x 512 16-bit FEI-style TIFFs (with a data bar and metadata, as the
fake lab's SEM does) into a folder at a steady rate, each in several chunks; the source
follows the folder with OS events (inotify) and with polling. For each frame it
records the time from the writer closing the file to ``acquire`` returning it (read,
metadata parsed, data bar cropped), and checks that every frame came once, in order,
whole. Reported per mode: frames, p50 / p99 / max latency, and frames missing or
repeated (both must be 0).

    ./dev bench watch                 # or: python bench/watch.py --frames 100 --rate 10
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from semservo import jsontext
from semservo.instruments import NotReady
from services.fakelab.acquisition import encode_fei_tiff, fei_metadata_text, with_data_bar
from services.imageserver.watch import WatchSource


def frame(index: int, rows: int = 512, cols: int = 512) -> np.ndarray:
    rng = np.random.default_rng(index)
    return (rng.random((rows, cols)) * 60000).astype(np.uint16)


def write_frames(folder: Path, count: int, rate: float, chunks: int, closed_at: dict) -> None:
    text = fei_metadata_text(pixel_size_nm=20.0, dwell_ns=100, working_distance_mm=5.0, rows=512, cols=512)
    for index in range(count):
        started = time.monotonic()
        data = encode_fei_tiff(with_data_bar(frame(index)), text)
        step = -(-len(data) // chunks)
        path = folder / f"frame{index:05d}.tif"
        with open(path, "wb") as file:
            for start in range(0, len(data), step):
                file.write(data[start: start + step])
                file.flush()
                time.sleep(0.002)
        closed_at[path.name] = time.monotonic()
        time.sleep(max(0.0, 1.0 / rate - (time.monotonic() - started)))


def run(mode: str, frames: int, rate: float, chunks: int) -> dict:
    with tempfile.TemporaryDirectory() as folder_name:
        folder = Path(folder_name)
        source = WatchSource(folder, settle_s=0.3, polling=mode == "polling")
        closed_at: dict[str, float] = {}
        writer = threading.Thread(target=write_frames, args=(folder, frames, rate, chunks, closed_at))
        writer.start()
        received: list[tuple[str, float]] = []
        deadline = time.monotonic() + frames / rate + 30
        try:
            while len(received) < frames and time.monotonic() < deadline:
                try:
                    image = source.acquire()
                except NotReady:
                    time.sleep(0.001)
                    continue
                received.append((image.label, time.monotonic()))
                assert image.pixels.shape == (512, 512)
        finally:
            writer.join()
            source.close()
        names = [name for name, _ in received]
        latencies_ms = np.array([(when - closed_at[name]) * 1000 for name, when in received if name in closed_at])
        expected = [f"frame{index:05d}.tif" for index in range(frames)]
        return {
            "mode": source.mode, "frames": len(received),
            "missing": len(set(expected) - set(names)), "repeated": len(names) - len(set(names)),
            "in_order": names == sorted(names),
            "p50_ms": float(np.percentile(latencies_ms, 50)), "p99_ms": float(np.percentile(latencies_ms, 99)),
            "max_ms": float(latencies_ms.max()),
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="frames per mode (default 60)")
    parser.add_argument("--rate", type=float, default=10.0, help="frames saved per second (default 10)")
    parser.add_argument("--chunks", type=int, default=8, help="writes per file (default 8)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    rows = []
    for mode in ("events", "polling"):
        print(f"{mode}: {args.frames} frames at {args.rate:g}/s, {args.chunks} chunks each ...", flush=True)
        rows.append(run(mode, args.frames, args.rate, args.chunks))
    print("\n| mode | frames | missing | repeated | in order | file closed -> frame p50 | p99 | max |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['mode']} | {row['frames']} | {row['missing']} | {row['repeated']} | {row['in_order']} | "
              f"{row['p50_ms']:.1f} ms | {row['p99_ms']:.1f} ms | {row['max_ms']:.1f} ms |")
    if args.json:
        args.json.write_text(jsontext.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
