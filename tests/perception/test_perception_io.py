"""Cloud files (.ply, .pcd, .npy) and the `extract` / `demo --sample` commands."""

import json
import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from bagit.cli import main
from bagit.common.errors import BadCloud
from bagit.common.geometry import points_to_polyline_distance
from bagit.services.perception import load_cloud
from bagit.services.perception.synthetic import make_rim_cloud


@pytest.fixture(scope="module")
def cloud_and_rim():
    return make_rim_cloud("lens", rpy=(0.2, 0.0, 0.4), n_points=6000, outlier_fraction=0.2, occlusion=0.07, seed=3)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".PLY"])
def test_ply_and_pcd_round_trip(tmp_path, cloud_and_rim, suffix):
    cloud, _ = cloud_and_rim
    path = tmp_path / f"c{suffix}"
    assert o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud)))
    got = load_cloud(path)
    assert got.dtype == np.float64 and np.allclose(got, cloud, atol=1e-6)


def test_npy_round_trip_any_numeric_dtype(tmp_path, cloud_and_rim):
    cloud, _ = cloud_and_rim
    for dtype in (np.float64, np.float32, np.int32):
        np.save(tmp_path / "c.npy", (cloud * 1000).astype(dtype))
        got = load_cloud(str(tmp_path / "c.npy"))
        assert got.dtype == np.float64 and got.shape == cloud.shape


@pytest.mark.parametrize(
    "name, content, word",
    [
        ("missing.ply", None, "no cloud file"),
        ("c.xyz", b"1 2 3\n", "unsupported"),
        ("noext", b"1 2 3\n", "unsupported"),
        ("junk.ply", b"this is not a ply file", "no points"),
        ("junk.pcd", b"\x00\x01garbage", "no points"),
        ("empty.ply", b"", "no points"),
        ("junk.npy", b"not numpy", "cannot read"),
    ],
)
def test_bad_files_raise_bad_cloud(tmp_path, name, content, word):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(BadCloud, match=word):
        load_cloud(path)


def test_bad_npy_arrays(tmp_path):
    cases = {
        "flat.npy": (np.zeros(9), "shape"),
        "four.npy": (np.zeros((5, 4)), "shape"),
        "none.npy": (np.zeros((0, 3)), "no points"),
        "text.npy": (np.array([["a", "b", "c"]]), "numeric"),
        "cplx.npy": (np.zeros((4, 3), complex), "numeric"),
    }
    for name, (arr, word) in cases.items():
        np.save(tmp_path / name, arr)
        with pytest.raises(BadCloud, match=word):
            load_cloud(tmp_path / name)
    np.save(tmp_path / "obj.npy", np.array([[1, "x", None]], dtype=object), allow_pickle=True)
    with pytest.raises(BadCloud, match="cannot read"):  # pickles are never loaded
        load_cloud(tmp_path / "obj.npy")


def test_a_directory_is_not_a_cloud(tmp_path):
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(BadCloud, match="not a file"):
        load_cloud(tmp_path / "d.ply")


def test_extract_command_json(tmp_path, capsys, cloud_and_rim):
    cloud, rim = cloud_and_rim
    path = tmp_path / "c.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud)))
    assert main(["extract", str(path), "--n-x", "24", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {"soi", "n_x", "n_points", "time_ms"}
    soi = np.asarray(out["soi"])
    assert soi.shape == (24, 3) and out["n_x"] == 24 and out["n_points"] == 6000 and out["time_ms"] > 0
    assert points_to_polyline_distance(soi, rim).mean() < 0.002


def test_extract_command_human_output_and_errors(tmp_path, capsys, cloud_and_rim):
    cloud, _ = cloud_and_rim
    np.save(tmp_path / "c.npy", cloud)
    assert main(["extract", str(tmp_path / "c.npy"), "--n-x", "8"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("SOI: 8 points from 6000") and len(text.strip().splitlines()) == 9
    assert main(["extract", str(tmp_path / "c.npy"), "--n-x", "3"]) == 2
    assert "--n-x" in capsys.readouterr().err
    np.save(tmp_path / "nan.npy", np.full((50, 3), np.nan))
    assert main(["extract", str(tmp_path / "nan.npy")]) == 2
    assert "NaN" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.processes
def test_demo_sample_in_a_fresh_process():
    res = subprocess.run(
        [sys.executable, "-m", "bagit.cli", "demo", "--sample", "--json"], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert np.asarray(out["soi"]).shape == (32, 3) and out["n_points"] == 12_000
