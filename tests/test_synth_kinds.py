"""Street kinds of ``streetcd synth`` (issue 16): each setting changes what it should and
nothing else, and the default street stays what it was, byte for byte."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import cv2
import laspy
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from streetcd import classes
from streetcd.cli.main import cli
from streetcd.errors import InputError
from streetcd.io.las import read_las
from streetcd.io.poses import read_opk_csv
from streetcd.synth import EPOCH2, generate_street, load_scene, render_depth
from streetcd.synth.kinds import PRESETS, ROLES, SCHEMES, StreetKind, resolve_kind
from streetcd.synth.layout import CURB_H, PAINTED_TYPES
from streetcd.synth.materials import PAINT

TINY = dict(seed=7, n_images=2, size=(160, 90), length_m=30.0)


def _manifest(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _points(manifest_path: Path) -> list[laspy.LasData]:
    m = _manifest(manifest_path)
    return [laspy.read(manifest_path.parent / f) for f in m["files"]["cloud"]]


def _classification(manifest_path: Path) -> np.ndarray:
    return np.concatenate([np.asarray(las.classification) for las in _points(manifest_path)])


@pytest.fixture(scope="module")
def default(tmp_path_factory) -> Path:
    return generate_street(tmp_path_factory.mktemp("default"), **TINY)


def _make(tmp_path_factory, name: str, **kw) -> Path:
    return generate_street(tmp_path_factory.mktemp(name), **TINY, **kw)


# --- the default street is unchanged ---------------------------------------------------------


def _content_digest(folder: Path) -> str:
    """One digest of a street folder: files byte for byte, LAZ files by their decoded points
    and point format (so that only what the generator decides counts, not the compressor)."""
    h = hashlib.sha256()
    for p in sorted(q for q in folder.rglob("*") if q.is_file()):
        h.update(str(p.relative_to(folder)).encode())
        if p.suffix == ".laz":
            las = laspy.read(p)
            h.update(str(las.header.point_format.id).encode())
            h.update(las.points.array.tobytes())
        else:
            h.update(p.read_bytes())
    return h.hexdigest()


# Digest of TINY's default street, taken before the street kinds were added and checked equal
# after (2026-11-25). Cached evaluation scenes and other tests depend on the default output:
# if a change to the generator alters it on purpose, say so in docs/DECISIONS.md and update.
DEFAULT_DIGEST = "675f0c7b7614ad7f8e5247337a9c11a03b9bd1dc6098e1819c2979971dd71632"


def _generated_with_avx2_kernels(out: Path, **kw) -> Path:
    """``generate_street(out, **TINY, **kw)`` in a Python of its own whose OpenBLAS runs its
    AVX2 (Haswell) kernels wherever the CPU has AVX2: OpenBLAS picks its kernels by CPU when
    numpy loads it, and its AVX-512 kernels round matrix products differently, so that an
    AVX-512 machine makes a street that differs in the last bits. The digest was taken with
    the AVX2 kernels (docs/DECISIONS.md, 2026-11-29, eleventh session)."""
    env = dict(os.environ)
    cpu = Path("/proc/cpuinfo")
    if platform.machine() == "x86_64" and cpu.exists() and " avx2" in cpu.read_text():
        env.setdefault("OPENBLAS_CORETYPE", "Haswell")
    code = (
        "import json, sys; from streetcd.synth import generate_street;"
        " print(generate_street(sys.argv[1], **json.loads(sys.argv[2])))"
    )
    args = json.dumps({**TINY, "size": list(TINY["size"]), **kw})
    done = subprocess.run(
        [sys.executable, "-c", code, str(out), args], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    return Path(done.stdout.strip().splitlines()[-1])


def test_default_street_is_byte_identical_to_before_the_kinds(default, tmp_path):
    first = _generated_with_avx2_kernels(tmp_path / "a")
    assert _content_digest(first.parent) == DEFAULT_DIGEST
    # the default kind spelled out gives the same files, and no kind entries in the manifest
    again = _generated_with_avx2_kernels(
        tmp_path / "b", kind="default", path="vehicle", colour=True
    )
    assert _content_digest(again.parent) == DEFAULT_DIGEST
    m = _manifest(default)
    assert "street_kind" not in m and "class_codes" not in m and "plain" not in m["generator"]
    assert not (default.parent / "streetcd.yaml").exists()


# --- colours, density ----------------------------------------------------------------------


def test_no_colour_writes_point_format_6_without_rgb_and_the_same_points(default, tmp_path_factory):
    grey = _make(tmp_path_factory, "grey", colour=False)
    for las in _points(grey):
        assert las.header.point_format.id == 6
        assert "red" not in las.point_format.dimension_names
    for f in _manifest(grey)["files"]["cloud"]:
        assert read_las(grey.parent / f).rgb is None
    a, b = _points(default), _points(grey)
    np.testing.assert_array_equal(
        np.concatenate([x.X for x in a]), np.concatenate([x.X for x in b])
    )
    assert _manifest(grey)["street_kind"]["colour"] is False


def test_density_keeps_that_share_of_the_points_and_spacing_thins_the_scan(
    default, tmp_path_factory
):
    full = _manifest(default)["scan"]["n_points"]
    tenth = _make(tmp_path_factory, "tenth", density=0.1)
    n = _manifest(tenth)["scan"]["n_points"]
    assert n == len(_classification(tenth))
    assert abs(n / full - 0.1) < 0.005, n / full
    coarse = _make(tmp_path_factory, "coarse", point_spacing_m=0.25)
    m = _manifest(coarse)
    assert m["scan"]["profile_spacing_m"] == pytest.approx(0.5)
    # a 5x coarser spacing in both directions: about 25x fewer points (fewer at long range)
    assert 0.02 < m["scan"]["n_points"] / full < 0.06, m["scan"]["n_points"] / full


# --- class codes --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["asprs", "city"])
def test_class_codes_in_the_cloud_match_the_written_config(default, tmp_path_factory, name):
    coded = _make(tmp_path_factory, f"codes-{name}", class_codes=name)
    config = yaml.safe_load((coded.parent / "streetcd.yaml").read_text(encoding="utf-8"))
    roles = config["detect"]["classes"]
    assert list(roles) == list(ROLES) and set(config) == {"detect"}
    assert all(isinstance(c, int) and 0 <= c <= 255 for v in roles.values() for c in v)
    # the same scan, point for point: each point's new code is one of its role's codes
    old, new = _classification(default), _classification(coded)
    role_of = {
        classes.GROUND: "ground",
        classes.ROAD: "road",
        classes.VEGETATION: "vegetation",
        classes.BUILDING: "building",
        classes.POLE: "pole",
        classes.SIGN: "sign",
        classes.RAILING: "railing",
        classes.FURNITURE: "furniture",
        classes.CAR: "vehicle",
    }
    for code in np.unique(old):
        written = set(np.unique(new[old == code]).tolist())
        assert written <= set(roles[role_of[int(code)]]), (int(code), written)
    if name == "asprs":
        assert int(new.max()) < 32  # fits the classification of LAS 1.2's formats
    else:  # several codes for a role: signs and boards
        assert set(np.unique(new).tolist()) >= set(SCHEMES["city"].roles["sign"])
    m = _manifest(coded)
    assert m["class_codes"]["config"] == "streetcd.yaml"
    assert {int(k) for k in m["classes"]} >= set(np.unique(new).tolist())


def test_a_type_of_its_own_gets_its_code_but_a_sign_post_stays_a_pole():
    city = SCHEMES["city"]
    objects = {
        1: {"type": "hedge", "class": classes.VEGETATION},
        2: {"type": "tree", "class": classes.VEGETATION},
        3: {"type": "sign", "class": classes.SIGN},
        4: {"type": "board", "class": classes.SIGN},
    }
    cls = np.array([classes.VEGETATION, classes.VEGETATION, classes.POLE, classes.SIGN, 65])
    obj = np.array([1, 2, 3, 3, 4])
    np.testing.assert_array_equal(city.codes(cls, obj, objects), [231, 230, 101, 102, 107])


def test_unclassified_cloud_is_all_class_1_and_custom_codes_come_from_a_file(
    tmp_path_factory, tmp_path
):
    sparse = dict(point_spacing_m=0.2)  # the codes do not need a dense cloud: quicker
    flat = _make(tmp_path_factory, "unclassified", class_codes="unclassified", **sparse)
    assert set(np.unique(_classification(flat)).tolist()) == {1}
    assert not (flat.parent / "streetcd.yaml").exists()
    spec = tmp_path / "mycity.yaml"
    codes = {r: [100 + i] for i, r in enumerate(ROLES)}
    spec.write_text(yaml.safe_dump({"detect": {"classes": codes}}), encoding="utf-8")
    mine = _make(tmp_path_factory, "custom", class_codes=str(spec), **sparse)
    written = yaml.safe_load((mine.parent / "streetcd.yaml").read_text(encoding="utf-8"))
    assert written["detect"]["classes"] == codes
    assert set(np.unique(_classification(mine)).tolist()) <= {c[0] for c in codes.values()}


def test_a_bad_class_codes_file_names_the_field(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text("detect:\n  classes:\n    ground: [2]\n    road: [300]\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"bad.yaml: field 'detect.classes.road'"):
        generate_street(tmp_path / "x", **TINY, class_codes=str(spec))
    with pytest.raises(InputError, match="class_codes"):
        resolve_kind(class_codes="klingon")


# --- camera paths -------------------------------------------------------------------------


@pytest.mark.parametrize("path", ["sidewalk-right", "sidewalk-left"])
def test_sidewalk_cameras_walk_the_sidewalk_at_eye_height(tmp_path_factory, path):
    mp = generate_street(
        tmp_path_factory.mktemp(path), seed=7, n_images=3, size=(320, 180), length_m=30.0, path=path
    )
    m = _manifest(mp)
    scene = load_scene(m)
    street = scene.streets[0]
    lay = street.layout
    rh, sw = lay["road_half_width_m"], lay["sidewalk_width_m"]
    views = read_opk_csv(mp.parent / m["files"]["poses_true_opk"]).views
    for v in views:
        local = v.local(scene.origin)
        c = street.to_street(local.pose.center[None])[0]
        forward = street.to_street(local.pose.R[2][None] + street.offset)[0]
        assert 1.5 <= c[2] - CURB_H <= 1.7  # eye height above the sidewalk
        if path == "sidewalk-right":  # on the near sidewalk, looking forward and across
            assert -(rh + sw) < c[1] < -rh
            yaw = np.degrees(np.arctan2(forward[1], forward[0]))
            assert 35 <= yaw <= 55, yaw
        else:  # on the far sidewalk, looking along the street towards the road
            assert rh < c[1] < rh + sw
            yaw = np.degrees(np.arctan2(forward[1], forward[0]))
            assert -25 <= yaw <= -10, yaw
    if path == "sidewalk-right":  # the far side's changes are seen obliquely from 10-20 m
        depths = []
        for v in views:
            mask = cv2.imread(str(mp.parent / f"truth/{Path(v.name).stem}.mask.png"), 0) > 0
            if mask.any():
                depth, _ = render_depth(scene, v, EPOCH2)
                depths.append(float(np.nanmedian(depth[mask])))
        assert depths and all(8.0 <= d <= 25.0 for d in depths), depths
    assert m["images"]["overlap_at_far_facade"] is None


# --- plain objects ----------------------------------------------------------------------


def test_plain_objects_are_uniformly_painted_and_stand_before_plain_walls(tmp_path_factory):
    size = dict(seed=7, n_images=2, size=(480, 270), length_m=30.0)
    textured = generate_street(tmp_path_factory.mktemp("textured"), **size)
    plain = generate_street(tmp_path_factory.mktemp("plain"), **size, plain=True)
    scene = load_scene(_manifest(plain))
    street = scene.streets[0]
    types = {o["id"]: o["type"] for o in scene.objects}
    for oid, t in types.items():
        if t in (*PAINTED_TYPES, "wall"):
            rows = street.obj == oid
            assert np.all(street.mat[rows] == PAINT), t
            assert len(np.unique(street.color[rows], axis=0)) == 1, t
    # the walls stand ~1 m behind the boards and benches of the sidewalk's middle
    walls = [o for o, t in types.items() if t == "wall"]
    assert walls
    wall_y = street.params[np.isin(street.obj, walls)][:, [1, 4]].mean()
    board_rows = np.isin(street.obj, [o for o, t in types.items() if t == "board"])
    board_y = street.params[board_rows & (street.kind == 0)][:, [1, 4]].mean(1).max()
    assert 0.8 <= wall_y - board_y <= 1.5, wall_y - board_y

    def local_std(folder: Path) -> dict[str, float]:
        """Median 5x5 grey-level std on flat painted objects' pixels, per type."""
        m = _manifest(folder)
        sc = load_scene(m)
        kinds = {o["id"]: o["type"] for o in m["objects"]}
        out: dict[str, list[float]] = {}
        for v in read_opk_csv(folder.parent / m["files"]["poses_true_opk"]).views:
            _, ids = render_depth(sc, v, EPOCH2)
            g = cv2.imread(str(folder.parent / "images" / v.name)).astype(np.float32).mean(2)
            mu = cv2.blur(g, (5, 5))
            sd = np.sqrt(np.maximum(cv2.blur(g * g, (5, 5)) - mu * mu, 0.0))
            for oid in np.unique(ids):
                t = kinds.get(int(oid))
                if t in ("board", "sign", "wall"):
                    inner = cv2.erode((ids == oid).astype(np.uint8), np.ones((5, 5), np.uint8))
                    if inner.sum() >= 20:
                        out.setdefault(t, []).append(float(np.median(sd[inner > 0])))
        return {t: float(np.median(v)) for t, v in out.items()}

    flat, busy = local_std(plain), local_std(textured)
    assert flat and max(flat.values()) < 3.0, flat  # sensor noise and JPEG only
    assert max(busy.values()) > 2 * max(flat.values()), (busy, flat)


# --- presets and the command line ---------------------------------------------------------


def test_presets_are_street_kinds_and_explicit_settings_override_them():
    assert PRESETS["default"] == StreetKind() and StreetKind().is_default
    k = resolve_kind("mixed", colour=True, density=None)
    assert k.path == "sidewalk-right" and k.plain and k.colour and k.density == 0.25
    with pytest.raises(InputError, match="kind"):
        resolve_kind("nope")
    with pytest.raises(InputError, match="density"):
        resolve_kind(density=0.0)
    with pytest.raises(InputError, match="path"):
        resolve_kind(path="tram")


def test_cli_kind_writes_the_class_map_and_lists_kinds_in_help(tmp_path):
    runner = CliRunner()
    help_text = runner.invoke(cli, ["synth", "--help"]).output
    for name in PRESETS:
        assert name in help_text
    out = tmp_path / "mixed"
    args = ["synth", "--out", str(out), "--seed", "7", "--images", "2", "--size", "160x90"]
    result = runner.invoke(cli, [*args, "--length", "30", "--kind", "mixed", "--density", "0.5"])
    assert result.exit_code == 0, result.output
    assert "class map" in result.output and (out / "streetcd.yaml").exists()
    m = _manifest(out / "manifest.json")
    assert m["street_kind"] == {
        "path": "sidewalk-right",
        "plain": True,
        "colour": False,
        "density": 0.5,
        "point_spacing_m": None,
        "class_codes": "asprs",
    }
    bad = runner.invoke(cli, [*args, "--density", "lots"])
    assert bad.exit_code != 0 and "0.3m" in bad.output
    bad = runner.invoke(cli, [*args, "--class-codes", "klingon"])
    assert bad.exit_code != 0 and "class_codes" in bad.output and "Traceback" not in bad.output


@pytest.mark.slow
def test_a_4000x3000_street_generates(tmp_path):
    mp = generate_street(tmp_path, seed=7, n_images=1, size=(4000, 3000), length_m=30.0)
    img = cv2.imread(str(tmp_path / "images" / "IMG_0000.jpg"))
    assert img.shape == (3000, 4000, 3)
    assert _manifest(mp)["images"]["width"] == 4000
