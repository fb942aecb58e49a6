"""The synthetic street: geometry agrees between the cloud and the images, the truth is
exactly what the renderer says changed, outputs are reproducible and readable."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from streetcd import classes
from streetcd.cli.main import cli
from streetcd.errors import InputError
from streetcd.geometry.camera import in_image, project
from streetcd.io.las import read_las
from streetcd.io.poses import read_opk_csv, read_poses
from streetcd.synth import (
    EPOCH1,
    EPOCH2,
    build_street_scene,
    generate_city,
    generate_street,
    load_scene,
    render_depth,
)
from streetcd.synth.raycast import BOX, CYL, ELL, build_grid, cast
from streetcd.types import PointCloud

SMALL = dict(n_images=6, size=(320, 180), length_m=40.0)


@pytest.fixture(scope="module")
def changed(tmp_path_factory) -> Path:
    return generate_street(tmp_path_factory.mktemp("changed"), seed=5, pose_noise_px=3.0, **SMALL)


@pytest.fixture(scope="module")
def unchanged(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("unchanged")
    result = CliRunner().invoke(
        cli,
        [
            "synth",
            "--out",
            str(out),
            "--seed",
            "5",
            "--images",
            "4",
            "--size",
            "320x180",
            "--length",
            "35",
            "--no-changes",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "points" in result.output and "images" in result.output
    return out / "manifest.json"


def _manifest(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _cloud(manifest_path: Path, origin: np.ndarray) -> PointCloud:
    m = _manifest(manifest_path)
    parts = [read_las(manifest_path.parent / f, origin=origin) for f in m["files"]["cloud"]]
    return PointCloud(
        np.concatenate([p.xyz for p in parts]),
        origin,
        np.concatenate([p.classification for p in parts]),
        crs=parts[0].crs,
    )


# --- the ray caster against closed-form intersections -------------------------------------


def test_raycast_hits_box_cylinder_ellipsoid_at_closed_form_distances():
    kind = np.array([BOX, CYL, ELL], np.int8)
    params = np.array(
        [
            [4.0, -1.0, 0.0, 5.0, 1.0, 2.0],  # box, front face x = 4
            [0.0, 10.0, 0.5, 0.0, 3.0, 0.0],  # cylinder at (0, 10), r = 0.5
            [-8.0, 0.0, 1.0, 1.0, 2.0, 0.5],
        ]
    )  # ellipsoid at (-8, 0, 1)
    grid = build_grid(kind, params, cell_m=1.0)
    o = np.zeros((4, 3))
    o[:, 2] = 1.0
    d = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])
    t, k, n = cast(grid, o, d)
    np.testing.assert_allclose(t[:3], [4.0, 9.5, 7.0], atol=1e-9)
    np.testing.assert_array_equal(k, [0, 1, 2, -1])
    np.testing.assert_allclose(n[:3], [[-1, 0, 0], [0, -1, 0], [1, 0, 0]], atol=1e-6)
    # a ray above the cylinder's top misses it; one from above hits its cap
    t2, k2, n2 = cast(
        grid,
        np.array([[0.0, 0.0, 3.5], [0.0, 10.2, 5.0]]),
        np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),
    )
    assert k2[0] == -1 and k2[1] == 1
    np.testing.assert_allclose([t2[1], *n2[1]], [2.0, 0, 0, 1], atol=1e-6)


# --- geometry: the cloud lies on the surfaces the camera sees -----------------------------


def test_unchanged_cloud_lies_on_rendered_surfaces_with_true_poses(unchanged):
    m = _manifest(unchanged)
    scene = load_scene(m)
    full = _cloud(unchanged, scene.origin)
    cloud = full.subset(np.arange(0, len(full), 3))  # every third point keeps the test quick
    street = scene.streets[0]
    views = read_opk_csv(unchanged.parent / m["files"]["poses_true_opk"]).views
    for view in views:
        depth, _ = render_depth(scene, view, EPOCH1)
        local = view.local(scene.origin)
        uv, z = project(cloud.xyz, local.intrinsics, local.pose)
        inside = in_image(uv, local.intrinsics, margin=-1.0) & (z > 1.0)
        pts = cloud.xyz[inside]
        # visible = nothing in the scene lies between the camera and the point, tested by a
        # ray through the point itself (not the pixel centre)
        c = street.to_street(local.pose.center[None])[0]
        rays = street.to_street(pts) - c
        dist = np.linalg.norm(rays, axis=1)
        t, _, _ = cast(street.grids[EPOCH1], np.broadcast_to(c, rays.shape), rays)
        sigma = np.clip(0.005 + 0.001 * 30.0, 0.005, 0.02)  # scan noise at the farthest ranges
        tol = 3 * sigma + 0.02
        visible = t * dist >= dist - tol
        assert visible.sum() > 2000, f"{view.name}: only {visible.sum()} visible points"
        assert 0.2 < visible.mean() < 1.0
        # the point's depth lies within the depths of the 4 pixel centres around it
        u, v = uv[inside][visible].T
        u0 = np.clip(np.floor(u).astype(int), 0, depth.shape[1] - 2)
        v0 = np.clip(np.floor(v).astype(int), 0, depth.shape[0] - 2)
        quad = np.stack(
            [depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]]
        )
        zv = z[inside][visible]
        ok = (zv >= np.nanmin(quad, 0) - tol) & (zv <= np.nanmax(quad, 0) + tol)
        assert ok.mean() >= 0.95, f"{view.name}: {ok.mean():.3f} of visible points on surface"


def test_unchanged_scene_has_no_changes_and_empty_truth(unchanged):
    m = _manifest(unchanged)
    assert m["changes"] == [] and m["disturbances"] == []
    scene = load_scene(m)
    for ob in scene.objects:
        assert ob["epochs"] == [1, 2], ob
    for v in m["views"]:
        for key in ("mask", "dontcare", "instances"):
            img = cv2.imread(str(unchanged.parent / v[key]), cv2.IMREAD_UNCHANGED)
            assert img.shape == (180, 320) and not img.any(), (v["name"], key)


# --- ground truth: exactly what the renderer says changed ---------------------------------


def test_change_masks_equal_renderer_visibility_of_changed_objects(changed):
    m = _manifest(changed)
    scene = load_scene(m)
    kinds = {c["kind"] for c in m["changes"]}
    assert {"added", "removed", "moved", "replaced"} <= kinds
    assert {"pole", "board", "railing", "sign", "bench"} <= {c["type"] for c in m["changes"]}
    epochs = {o["id"]: o["epochs"] for o in m["objects"]}
    inst_of = {o: c["instance_id"] for c in m["changes"] for o in c["objects"]}
    new = np.array([o for o in inst_of if epochs[o] == [2]])
    gone = np.array([o for o in inst_of if epochs[o] == [1]])
    views = read_opk_csv(changed.parent / m["files"]["poses_true_opk"]).by_name()
    n_changed = 0
    for v in m["views"]:
        _, ids2 = render_depth(scene, views[v["name"]], EPOCH2)
        _, ids1 = render_depth(scene, views[v["name"]], EPOCH1)
        expected = np.isin(ids2, new) | np.isin(ids1, gone)
        mask = cv2.imread(str(changed.parent / v["mask"]), cv2.IMREAD_UNCHANGED)
        inst = cv2.imread(str(changed.parent / v["instances"]), cv2.IMREAD_UNCHANGED)
        assert inst.dtype == np.uint16
        np.testing.assert_array_equal(mask > 0, expected, err_msg=v["name"])
        assert (mask.any()) == bool(v["changed_instances"])
        assert sorted(set(np.unique(inst[inst > 0]).tolist())) == v["changed_instances"]
        n_changed += bool(v["changed_instances"])
    assert n_changed >= 1
    assert all(c["views"] for c in m["changes"]), "every change is seen by some image"


def test_disturbances_are_dontcare_and_never_changes(changed):
    m = _manifest(changed)
    kinds = {d["kind"] for d in m["disturbances"]}
    assert {"car", "pedestrian"} <= kinds
    total = 0
    for v in m["views"]:
        mask = cv2.imread(str(changed.parent / v["mask"]), cv2.IMREAD_UNCHANGED)
        dc = cv2.imread(str(changed.parent / v["dontcare"]), cv2.IMREAD_UNCHANGED)
        assert not np.any((mask > 0) & (dc > 0))
        total += int(np.count_nonzero(dc))
    assert total > 0


# --- reproducibility -------------------------------------------------------------------------


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def test_same_seed_gives_byte_identical_files(changed, tmp_path):
    again = generate_street(tmp_path / "again", seed=5, pose_noise_px=3.0, **SMALL)
    first, second = _digests(changed.parent), _digests(again.parent)
    # manifest, 4 pose files, true poses, and per image: JPEG, mask, instances, don't-care
    assert len(first) == 1 + 4 + 1 + 6 * 4 + len(_manifest(changed)["files"]["cloud"])
    assert first == second


def test_different_seed_gives_a_different_street():
    a, b = build_street_scene(1, 40.0), build_street_scene(2, 40.0)
    assert not np.array_equal(a.origin, b.origin)
    pa, pb = a.streets[0].params, b.streets[0].params
    assert pa.shape != pb.shape or not np.allclose(pa, pb)


# --- poses --------------------------------------------------------------------------------


def test_pose_noise_gives_requested_rms_reprojection_error(changed):
    m = _manifest(changed)
    assert abs(m["pose_noise"]["achieved_rms_px"] - 3.0) < 0.15
    origin = np.array(m["origin"])
    cloud = _cloud(changed, origin)
    true = read_opk_csv(changed.parent / m["files"]["poses_true_opk"]).by_name()
    written = read_poses(changed.parent / m["files"]["poses_colmap"]).by_name()
    sq, n = 0.0, 0
    for name, t in true.items():
        tl, wl = t.local(origin), written[name].local(origin)
        xyz = cloud.xyz[::7]  # a sample is plenty for an RMS
        uv, z = project(xyz, tl.intrinsics, tl.pose)
        sel = in_image(uv, tl.intrinsics) & (z > 1.0) & (z < 40.0)
        uv2, _ = project(xyz[sel], wl.intrinsics, wl.pose)
        err = np.linalg.norm(uv2 - uv[sel], axis=1)
        sq += float(np.sum(err**2))
        n += len(err)
    rms = np.sqrt(sq / n)
    assert 2.2 < rms < 3.8, rms


def test_zero_pose_noise_writes_the_true_poses(unchanged):
    m = _manifest(unchanged)
    true = read_opk_csv(unchanged.parent / m["files"]["poses_true_opk"]).by_name()
    written = read_poses(unchanged.parent / m["files"]["poses_colmap"])
    for v in written.views:
        np.testing.assert_allclose(v.pose.R, true[v.name].pose.R, atol=1e-12)
        np.testing.assert_allclose(v.center, true[v.name].center, atol=1e-6)
    assert m["pose_noise"]["achieved_rms_px"] == 0.0


# --- readers round-trip what synth writes --------------------------------------------------


def test_readers_round_trip_the_outputs(changed):
    m = _manifest(changed)
    folder = changed.parent
    origin = np.array(m["origin"])
    codes = {
        classes.GROUND,
        classes.ROAD,
        classes.VEGETATION,
        classes.BUILDING,
        classes.POLE,
        classes.SIGN,
        classes.RAILING,
        classes.FURNITURE,
        classes.CAR,
    }
    total = 0
    for f in m["files"]["cloud"]:
        pc = read_las(folder / f)
        assert pc.crs == m["crs"] == "EPSG:32648"
        assert set(np.unique(pc.classification).tolist()) <= codes
        assert pc.rgb is not None and pc.intensity is not None and pc.gps_time is not None
        assert np.all(np.diff(pc.gps_time) >= 0)
        world = pc.xyz + pc.origin
        assert 370_000 < world[:, 0].min() and world[:, 0].max() < 375_000
        assert 142_000 < world[:, 1].min() and world[:, 1].max() < 146_000
        total += len(pc)
    assert total == m["scan"]["n_points"] > 100_000
    colmap = read_poses(folder / m["files"]["poses_colmap"], image_dir=folder / "images")
    opk = read_poses(folder / m["files"]["poses_opk"])
    assert colmap.crs == opk.crs == m["crs"]
    assert [v.name for v in colmap.views] == [v["name"] for v in m["views"]]
    for a, b in zip(colmap.views, opk.views, strict=True):
        np.testing.assert_allclose(a.pose.R, b.pose.R, atol=1e-9)
        np.testing.assert_allclose(a.center, b.center, atol=1e-6)
        img = cv2.imread(str(a.image))
        assert img.shape == (a.intrinsics.height, a.intrinsics.width, 3)
        assert np.linalg.norm(a.center - origin) < 200


def test_cloud_density_on_far_facades_is_in_the_papers_range(changed):
    m = _manifest(changed)
    scene = load_scene(m)
    street = scene.streets[0]
    cloud = _cloud(changed, scene.origin)
    p = street.to_street(cloud.xyz[cloud.classification == classes.BUILDING])
    y_face = street.layout["far_facade_y_m"]
    on = (np.abs(p[:, 1] - y_face) < 0.06) & (p[:, 2] > 1.0) & (p[:, 2] < 7.0)
    cells = np.floor(p[on][:, [0, 2]]).astype(int)
    _, counts = np.unique(cells, axis=0, return_counts=True)
    density = np.median(counts[counts > 50])  # points per m² on visible 1 m² façade cells
    assert 200 <= density <= 900, density


# --- the small city and argument checks --------------------------------------------------


def test_city_has_one_archive_one_pose_set_and_changes_in_some_streets(tmp_path):
    calls: list[tuple[int, int]] = []
    path = generate_city(
        tmp_path,
        seed=2,
        n_streets=2,
        images_per_street=2,
        size=(160, 90),
        length_m=30.0,
        progress=lambda done, total: calls.append((done, total)),
    )
    done = [d for d, _ in calls]
    assert done == sorted(done) and calls[-1][0] == calls[-1][1] == calls[0][1]
    m = _manifest(path)
    assert len(m["streets"]) == 2 and len(m["views"]) == 4
    streets_with_changes = {c["street"] for c in m["changes"]}
    assert streets_with_changes == {0}
    poses = read_poses(tmp_path / m["files"]["poses_opk"])
    assert {v.name for v in poses.views} == {v["name"] for v in m["views"]}
    files = m["files"]["cloud"]
    assert {f.split("/")[1].split("_")[0] for f in files} == {"street0", "street1"}


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(length_m=10.0), "length_m"),
        (dict(n_images=0), "number of images"),
        (dict(pose_noise_px=-1.0), "pose_noise_px"),
    ],
)
def test_bad_arguments_name_the_field(tmp_path, kwargs, field):
    with pytest.raises(InputError, match=field):
        generate_street(tmp_path, **kwargs)
