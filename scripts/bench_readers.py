#!/usr/bin/env python3
"""Reading frames: how a reader process is best started, and which decoder is fastest, measured in one run.

    python scripts/bench_readers.py [DATA] [--frames N] [--rounds R]

- ``start``: seconds from asking for a reader process to its first answer, for the ways a process can be
  started: a fresh interpreter running ``ti_fusion.io.frame_workers`` only (what ``Prefetcher`` does),
  multiprocessing's ``spawn`` and ``forkserver`` (both also run the caller's ``__main__`` script in the
  child or its server, which breaks a script without a ``__main__`` guard) and ``fork`` (of this process, which
  has imported Taichi and started it, as the pipeline's would have: unsafe, timed for comparison only).
- ``decode``: milliseconds per image of DATA's first N 16-bit depth PNGs and colour JPEGs (7-Scenes
  layout), OpenCV (``cv2.imdecode``) against imagecodecs (``png_decode``, ``jpeg8_decode``), pyspng
  (libspng) and simplejpeg (libjpeg-turbo) where they are installed, the decoders alternated image by image in each of R rounds (the median per decoder is printed),
  results checked equal; one thread each (``cv2.setNumThreads(1)``), as in a reader process.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen-7scenes"


def _answer(conn) -> None:
    import ti_fusion.io.frame_workers  # noqa: F401 (what a reader imports before its first frame)
    import ti_fusion.io.datasets.sevenscenes  # noqa: F401

    conn.send("ready")
    conn.close()


def _time_mp(method: str) -> float:
    ctx = mp.get_context(method)
    ours, theirs = ctx.Pipe()
    t = time.perf_counter()
    proc = ctx.Process(target=_answer, args=(theirs,))
    proc.start()
    ours.recv()
    elapsed = time.perf_counter() - t
    proc.join()
    return elapsed


def _time_interpreter() -> float:
    code = (f"import sys; sys.path[:] = {sys.path!r}; import ti_fusion.io.frame_workers, "
            "ti_fusion.io.datasets.sevenscenes; print('ready', flush=True)")
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    proc.stdout.readline()
    elapsed = time.perf_counter() - t
    proc.wait()
    return elapsed


def bench_start(rounds: int) -> None:
    from ti_fusion.backend import init_backend

    init_backend("cpu")  # the pipeline's process has started Taichi before it reads a frame
    ways = {"fresh interpreter (Prefetcher)": _time_interpreter, "multiprocessing spawn": lambda: _time_mp("spawn"),
            "multiprocessing forkserver": lambda: _time_mp("forkserver"),
            "multiprocessing fork (after Taichi started)": lambda: _time_mp("fork")}
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(rounds):  # alternated, so that the machine's load falls on each alike
        for name, way in ways.items():
            times[name].append(way())
    print("reader process start, to its first answer (s): median (min-max) of", rounds)
    for name, ts in times.items():
        print(f"  {name:<46} {statistics.median(ts):.3f} ({min(ts):.3f}-{max(ts):.3f})")


def _first_channel(image: np.ndarray) -> np.ndarray:
    """The grey channel of libspng's grey + alpha decoding of a 16-bit PNG with a transparency chunk (libspng
    has no 16-bit grey output), as a contiguous array like OpenCV's."""
    return np.ascontiguousarray(image[..., 0]) if image.ndim == 3 else image


def _version(dist: str) -> str:
    from importlib import metadata

    return metadata.version(dist)


def bench_decode(data: Path, frames: int, rounds: int) -> None:
    import cv2

    cv2.setNumThreads(1)
    depth = [np.fromfile(str(p), np.uint8) for p in sorted(data.glob("*depth.png"))[:frames]]
    color = [np.fromfile(str(p), np.uint8) for p in sorted(data.glob("*color.jpg"))[:frames]]
    decoders = {"png": {"OpenCV": lambda d: cv2.imdecode(d, cv2.IMREAD_UNCHANGED)},
                "jpeg": {"OpenCV": lambda d: cv2.cvtColor(cv2.imdecode(d, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)}}
    try:
        import imagecodecs

        decoders["png"][f"imagecodecs {imagecodecs.__version__}"] = imagecodecs.png_decode
        decoders["jpeg"][f"imagecodecs {imagecodecs.__version__}"] = imagecodecs.jpeg8_decode
    except ImportError:
        print("imagecodecs is not installed")
    try:
        import pyspng

        decoders["png"][f"pyspng {_version('pyspng')}"] = lambda d: _first_channel(pyspng.load(d.tobytes()))
    except ImportError:
        print("pyspng is not installed")
    try:
        import simplejpeg

        decoders["jpeg"][f"simplejpeg {simplejpeg.__version__}"] = lambda d: simplejpeg.decode_jpeg(d, colorspace="RGB")
    except ImportError:
        print("simplejpeg is not installed")
    print(f"decoding {data.name}'s first {frames} images, ms per image: median of {rounds} rounds "
          f"(each round the decoders alternate image by image)")
    for kind, images in (("png", depth), ("jpeg", color)):
        if not images:
            continue
        ways = decoders[kind]
        first = [f(images[0]) for f in ways.values()]
        assert all(np.array_equal(first[0], x) for x in first[1:]), f"the {kind} decoders disagree"
        per_round: dict[str, list[float]] = {name: [] for name in ways}
        for _ in range(rounds):
            spent = dict.fromkeys(ways, 0.0)
            for image in images:
                for name, f in ways.items():
                    t = time.perf_counter()
                    f(image)
                    spent[name] += time.perf_counter() - t
            for name in ways:
                per_round[name].append(1e3 * spent[name] / len(images))
        base = statistics.median(per_round["OpenCV"])
        for name, ms in per_round.items():
            m = statistics.median(ms)
            print(f"  {kind:<5} {name:<24} {m:6.2f} ms  ({min(ms):.2f}-{max(ms):.2f}; {base / m:.2f}x OpenCV)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="?", default=str(DEFAULT_DATA))
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--only", choices=("start", "decode"), default=None)
    args = parser.parse_args()
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; "
          f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC")
    if args.only in (None, "decode"):
        bench_decode(Path(args.data), args.frames, args.rounds)
    if args.only in (None, "start"):
        bench_start(args.rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
