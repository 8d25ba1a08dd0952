"""`bagit calibrate`: the camera's pose in the world from a view of the ChArUco board, into a rig YAML.

Lay the board (`--print-board board.png` writes the image to print; its size and world pose are the
rig config's `board:` section) where the rig config says, then calibrate from a live RealSense
(default), a RealSense recording (`--file`) or a colour image (`--image`, intrinsics from the rig
config). `--write` saves the rig config with the calibrated camera pose (and, from a RealSense, its
intrinsics, depth scale and serial).
"""

from __future__ import annotations

import argparse
from typing import Any

from bagit.commands import _args

NAME = "calibrate"
HELP = "estimate the camera-to-world extrinsics from a ChArUco board and write them into a rig config"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig-config", metavar="YAML", help="rig config with the board's pose (default: the built-in rig)")
    p.add_argument("--write", metavar="YAML", help="write the rig config with the calibrated camera here")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--file", metavar="REC", help="a RealSense recording (.db3 / .bag) of the board")
    src.add_argument("--image", metavar="PNG", help="a colour image of the board (intrinsics from the rig config)")
    src.add_argument("--print-board", metavar="PNG", help="only write the board image to print, and stop")
    p.add_argument("--serial", help="live RealSense serial (default: the rig config's, or the only one attached)")
    p.add_argument("--frames", type=_args.positive_int, default=10, metavar="N", help="frames to average from a camera or recording (default 10)")


def _frames_from_image(path: str, rig) -> list:
    import cv2
    import numpy as np

    from bagit.common.errors import CameraError
    from bagit.common.messages import RgbdFrame

    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise CameraError(f"cannot read image {path}")
    info = rig.camera.info()
    if (img.shape[1], img.shape[0]) != (info.width, info.height):
        raise CameraError(f"{path} is {img.shape[1]}x{img.shape[0]}, the rig camera {info.width}x{info.height}")
    rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return [RgbdFrame(camera=info, color=rgb, depth=np.zeros(rgb.shape[:2], np.uint16))]


def run(args: argparse.Namespace) -> dict[str, Any]:
    import cv2
    import numpy as np
    from scipy.spatial.transform import Rotation

    from bagit.commands._service import flagged_camera
    from bagit.common.errors import CameraError
    from bagit.common.geometry import matrix_to_rpy
    from bagit.common.rig import RigConfig
    from bagit.services.perception.calibration import calibrate_extrinsics
    from bagit.services.perception.sources import RealSenseSource, SourceConfig

    rig = RigConfig.from_file(args.rig_config) if args.rig_config else RigConfig()
    if args.print_board:
        if not cv2.imwrite(args.print_board, rig.board.image()):
            raise CameraError(f"cannot write {args.print_board}")
        w, h = rig.board.size()
        return {"success": True, "board_image": args.print_board, "board_m": [w, h]}
    if not 1 <= args.frames <= 1000:
        raise CameraError(f"--frames must be in 1..1000, got {args.frames}")
    camera = rig.camera
    if args.image:
        frames = _frames_from_image(args.image, rig)
        source = "image"
    else:
        cfg = SourceConfig(kind="realsense-file" if args.file else "realsense", path=args.file, real_time=False)
        with RealSenseSource(cfg, flagged_camera(camera, serial=args.serial)) as src:  # (open_source without the zenoh case)
            frames = []
            while len(frames) < args.frames and (f := src.read()) is not None:
                frames.append(f)
            i = src.info
            camera = camera.model_copy(update={"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy,
                                               "depth_scale": i.depth_scale, "serial": src.serial or camera.serial})
            source = f"{cfg.kind} {src.serial}"
    cal = calibrate_extrinsics(frames, rig.board)
    T_old = rig.camera.T_world_camera()
    T = cal.T_world_camera
    moved_m = float(np.linalg.norm(T[:3, 3] - T_old[:3, 3]))
    turned_deg = float(np.degrees(Rotation.from_matrix(T_old[:3, :3].T @ T[:3, :3]).magnitude()))
    out = rig.model_copy(update={"camera": camera.with_pose(T)})
    if args.write:
        from pathlib import Path

        try:
            Path(args.write).write_text(out.to_yaml(), encoding="utf-8")
        except OSError as e:
            raise CameraError(f"cannot write {args.write}: {e}") from None
    return {
        "success": True,
        "source": source,
        "frames": cal.frames,
        "corners": cal.corners,
        "reprojection_px": cal.reprojection_px,
        "spread_m": cal.spread_m,
        "spread_deg": cal.spread_deg,
        "T_world_camera": T,
        "position": T[:3, 3],
        "rpy": matrix_to_rpy(T[:3, :3]),
        "moved_m": moved_m,
        "turned_deg": turned_deg,
        "written": args.write,
    }


def human(r: dict[str, Any]) -> str:
    if "board_image" in r:
        return f"board image written to {r['board_image']} (print it {r['board_m'][0]:.3f} x {r['board_m'][1]:.3f} m)"
    p = ", ".join(f"{x:.4f}" for x in r["position"])
    rpy = ", ".join(f"{x:.4f}" for x in r["rpy"])
    s = (f"camera at ({p}) m, rpy ({rpy}) rad from {r['frames']} frame(s), {r['corners']} corners, "
         f"{r['reprojection_px']:.2f} px; {r['moved_m'] * 1000:.1f} mm / {r['turned_deg']:.2f} deg from the rig config")
    return s + (f"; written to {r['written']}" if r["written"] else "")
