"""Recording throughput: how fast `RecordingWriter` turns RGB-D frames into MCAP on this disk.

    python -m bagit.bench.recorder [--quick]

A 640x480 frame (uint8 colour + uint16 depth, 1.54 MB on the wire) goes through what the
recorder does per message: wire decode, JSON record (arrays base64), chunk compression, write.
Two frame kinds: a simulated one (MuJoCo render of exp01 with sensor noise: what a run records)
and uniform noise (incompressible: the worst case). Reported: frames/s and wire MB/s the writer
sustains flat out (30 Hz needs 30 frames/s, 46 MB/s), the file MB per recorded second at 30 Hz,
and the per-frame cost; per compression (zstd, lz4, none).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.common import stats_ms
from bagit.common import wire
from bagit.common.messages import RgbdFrame
from bagit.services.recorder.writer import RecorderConfig, RecordingWriter


def _sim_frame() -> RgbdFrame:
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.sim.world import SimWorld

    w = SimWorld(Scenario.from_file(find_scenario("exp01")), seed=0)
    try:
        return w.render_rgbd(0)
    finally:
        close = getattr(w, "close", None)
        if close is not None:
            close()


def _noise_frame() -> RgbdFrame:
    rng = np.random.default_rng(0)
    return RgbdFrame(color=rng.integers(0, 255, (480, 640, 3), dtype=np.uint8),
                     depth=rng.integers(300, 3000, (480, 640), dtype=np.uint16))


def _one(payload: bytes | bytearray, n: int, compression: str) -> dict[str, Any]:
    d = Path(tempfile.mkdtemp(prefix="bagit-bench-rec-"))
    try:
        w = RecordingWriter(RecorderConfig(dir=d, compression=compression, flush_s=1.0), "bench")
        per: list[float] = []
        t_ns = time.time_ns()
        t0 = time.perf_counter()
        for i in range(n):
            a = time.perf_counter()
            msg: RgbdFrame = wire.decode(payload)
            w.write("bagit/bench/camera/rgbd", msg, t_ns + int(i * 1e9 / 30))
            w.tick()
            per.append((time.perf_counter() - a) * 1e3)
        w.close()
        wall = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in d.glob("*.mcap"))
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return {
        "frames": n,
        "frames_per_s": n / wall,
        "wire_MB_per_s": n * len(payload) / wall / 1e6,
        "file_MB_per_recorded_s_at_30Hz": size / (n / 30) / 1e6,
        "file_bytes_per_wire_byte": size / (n * len(payload)),
        "keeps_up_at_30Hz": n / wall >= 30,
        "per_frame": stats_ms(per),
    }


def run(quick: bool = False) -> dict[str, Any]:
    n = 20 if quick else 90
    out: dict[str, Any] = {}
    for name, make in (("sim", _sim_frame), ("noise", _noise_frame)):
        payload = wire.encode(make())
        out[name] = {"wire_MB_per_frame": len(payload) / 1e6}
        for comp in ("zstd", "lz4", "none"):
            out[name][comp] = _one(payload, n, comp)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    print(json.dumps(run(quick=p.parse_args().quick), indent=1))


if __name__ == "__main__":
    main()
