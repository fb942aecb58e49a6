"""Parameter dataclasses: paper defaults, validation, YAML round trip."""

import dataclasses

import pytest

from streetcd.config import (
    AppearanceParams,
    ClassMap,
    Config,
    CorrelateParams,
    DetectParams,
    GraphCutParams,
    LocateParams,
    RefineParams,
    RunParams,
    SegmentParams,
    SurfaceParams,
    TextureParams,
    ZBufferParams,
    config_from_dict,
    config_to_dict,
    load_config,
    params_from_dict,
    params_to_dict,
    scale_px,
)
from streetcd.errors import InputError


def test_paper_defaults():
    p = DetectParams()
    z = p.zbuffer
    assert (
        z.block_window_px,
        z.weighted_window_px,
        z.gamma_px,
        z.delta_color,
        z.tau,
        z.max_angle_deg,
    ) == (5, 15, 100.0, 10.0, 0.5, 45.0)
    assert (p.surface.max_depth_jump_m, p.surface.max_edge_px) == (0.5, 30.0)
    g = p.graphcut
    assert (g.a, g.b, g.superpixel_cell_px, g.compactness, g.class_penalty, g.speckle_min_px) == (
        45.0,
        11.0,
        50.0,
        20.0,
        400.0,
        200,
    )


def test_params_are_frozen_and_validated():
    with pytest.raises(dataclasses.FrozenInstanceError):
        DetectParams().graphcut.a = 3  # type: ignore[misc]
    with pytest.raises(InputError, match="tau = 1.5"):
        ZBufferParams(tau=1.5)
    with pytest.raises(InputError, match="beta"):
        GraphCutParams(beta=-1)
    # every list of class codes: integers 0-255, refused at load with the setting's name
    lists = [
        ("refine", "apart_classes"),
        ("texture", "classes"),
        ("texture", "see_through_classes"),
        ("appearance", "classes"),
        ("correlate", "low_weight_classes"),
        ("surface", "spacing_edge_classes"),
    ]
    for block, key in lists:
        for bad in ([300], ["car"], [True], 5):
            with pytest.raises(InputError, match=rf"{key} = .* must be codes 0-255"):
                params_from_dict({block: {key: bad}})
        assert getattr(params_from_dict({block: {key: [64]}}), block).__dict__[key] == (64,)
    assert params_from_dict({"refine": {"apart_classes": []}}).refine.apart_classes == ()


def test_dict_round_trip_and_unknown_keys():
    p = params_from_dict({"graphcut": {"beta": 2.5}, "correlate": {"stretch_percentiles": [2, 98]}})
    assert p.graphcut.beta == 2.5 and p.correlate.stretch_percentiles == (2, 98)
    assert params_from_dict(params_to_dict(p)) == p
    with pytest.raises(InputError, match="unknown parameter"):
        params_from_dict({"graphcut": {"betta": 1}})


def test_default_yaml_is_the_paper_defaults(tmp_path):
    from pathlib import Path

    default = Path(__file__).parents[1] / "configs" / "default.yaml"
    if not default.exists():
        pytest.fail(f"{default} is missing")
    assert load_config(default).detect == DetectParams()
    assert load_config(None) == Config()


def test_one_config_file_sets_the_detector_and_the_run(tmp_path):
    path = tmp_path / "night.yaml"
    path.write_text(
        "detect:\n  correlate:\n    n_neighbours: 2\n"
        "run:\n  batch_size: 8\n  min_region_fraction: 0.01\n  segments:\n    max_gap_m: 12.5\n"
    )
    config = load_config(path)
    assert config.detect.correlate.n_neighbours == 2
    assert (config.run.batch_size, config.run.min_region_fraction) == (8, 0.01)
    assert config.run.segments == SegmentParams(max_gap_m=12.5)
    assert config_from_dict(config_to_dict(config)) == config
    with pytest.raises(InputError, match="unknown block"):
        config_from_dict({"detect": {}, "pipeline": {}})
    with pytest.raises(InputError, match=r"run: unknown parameter\(s\) batchsize"):
        config_from_dict({"run": {"batchsize": 2}})
    with pytest.raises(InputError, match="run.batch_size = 0"):
        RunParams(batch_size=0)
    with pytest.raises(InputError, match="config file not found"):
        load_config(tmp_path / "missing.yaml")
    path.write_text("detect:\n  texture:\n    weight: nan\n")  # a string to YAML
    with pytest.raises(InputError, match=r"night.yaml: detect.texture.weight = 'nan' must be"):
        load_config(path)
    path.write_text("run:\n  write_overlays: 1\n")
    with pytest.raises(InputError, match=r"run.write_overlays = 1 must be a bool"):
        load_config(path)
    path.write_text("detect: [1, 2\n")
    with pytest.raises(InputError, match=r"night.yaml: not valid YAML \(line 2, column 1\)"):
        load_config(path)
    # a number out of its range names the file and the block it was given in
    path.write_text("detect:\n  surface:\n    spacing_edge_factor: -1\n")
    with pytest.raises(
        InputError, match=r"night.yaml: detect.surface: parameter spacing_edge_factor = -1 must"
    ):
        load_config(path)
    path.write_text("detect:\n  texture:\n    min_foreshortening: .nan\n")
    with pytest.raises(InputError, match=r"night.yaml: detect.texture: .* = nan must be in"):
        load_config(path)
    path.write_text("run:\n  segments:\n    max_candidates: 1\n")  # below n_neighbours (3)
    with pytest.raises(InputError, match=r"night.yaml: parameter run.segments.max_candidates"):
        load_config(path)


def test_the_results_hash_covers_exactly_what_changes_results():
    base = Config()
    # pinned: a change of this number re-detects every view of every index on the next night,
    # so it must come from a change of the results (2026-11-30, the thirty-sixth round: a
    # dark colour's chromaticity tends to grey, appearance.dark_grey; 602513b9b3dede40
    # before, from the thirty-fifth round: the
    # hue of the vegetation and the façades below the camera checked against the cloud's
    # colours; 6b2eed8cd84feba7 for a commit with the vegetation alone, never a night's;
    # 2ff0c80dc14ddbcc before, from the thirty-second round: the
    # texture cue's near layer and the colour check's holes not near poles;
    # 1d6f3ec9e30c7274 before, from the thirty-first round: the
    # near points of poles, signs and furniture fill their surface between them;
    # d4fdd1d909361d52 before, from the thirtieth round: the
    # ground's reference colours checked where the cloud tells its road from it;
    # 50c1033411893261 before, from 2026-11-29, the twenty-eighth round: each region's depth
    # fraction (detect.locate), which the change objects read;
    # 41d92911d6fdb382 before, from the twenty-sixth round: an
    # old vehicle's changed pixels cut apart from the others' (refine.apart_classes);
    # 5f58a3c42a72f9a6 before, from the twenty-fourth round: the
    # near-depth band ends at the near object's outline in the view, and from the twenty-fifth
    # round each neighbour's registration shift (27e71fcf2b40181e without it); 029b331307b07b3f
    # before,
    # from the twenty-third round: the
    # second-smallest difference only where the view does not show the old colour;
    # 1be77a783281f300 before, from the twenty-first round: eq. 5's
    # second-smallest difference where three neighbours see a pixel; 0068d660689c1b69 before,
    # from the nineteenth round: the
    # see-through test's low-pass at the texture cue's working size, its version 2 in the hash;
    # 4c3d4d55ea75a55b before, from the eighteenth round: the see-through test on railings on
    # by default; d6f5f4c2c16f882a before that, from the seventeenth
    # round: the sparse-cloud surface on by default and the inferred roles' rules version 3, a
    # railing's foot; b391d095e4e6e3b2 before that, from the sixteenth round: the rules of the
    # inferred roles, version 2, and the texture cue's foreshortening test; 7fee81a419188dbe
    # before that, from the eighth round; 55a05b5c9150e8fc before that)
    assert base.results_hash() == "13478e666017c0eb"
    # the thirty-seventh round's switch, left off: on, it is hashed
    both_colours = AppearanceParams(raw_reference=True)
    assert Config(DetectParams(appearance=both_colours)).results_hash() == "89b01ee6a0c2feba"
    # dark towards black as before: the thirty-fifth round's hash holds
    to_black = AppearanceParams(dark_grey=False)
    assert Config(DetectParams(appearance=to_black)).results_hash() == "602513b9b3dede40"
    # the hue check off too: the thirty-second round's hash holds; every hash below was
    # made before either existed and is built without them
    no_hue = AppearanceParams(hue_classes=(), dark_grey=False)
    assert Config(DetectParams(appearance=no_hue)).results_hash() == "2ff0c80dc14ddbcc"
    # the thirty-third round's floor for coloured clouds, a switch left off: on, it is hashed
    floored_colours = TextureParams(see_through_colour_blur_px=1.5)
    assert (
        Config(DetectParams(texture=floored_colours, appearance=no_hue)).results_hash()
        == "26f5e1eea8c8e657"
    )
    floorless = TextureParams()
    # each of the thirty-second round's two changes off alone, then both: the thirty-first
    # round's hash holds
    near_off = TextureParams(near_layer_m=0.0, see_through_colour_blur_px=0.0)
    any_holes = AppearanceParams(hole_classes=(), hue_classes=(), dark_grey=False)
    assert (
        Config(DetectParams(texture=near_off, appearance=no_hue)).results_hash()
        == "57b76b36ebbe1c97"
    )
    assert (
        Config(DetectParams(texture=floorless, appearance=any_holes)).results_hash()
        == "28563640f6249c72"
    )
    assert (
        Config(DetectParams(texture=near_off, appearance=any_holes)).results_hash()
        == "1d6f3ec9e30c7274"
    )
    # the near points' fill off too (the thirty-first round's surface.point_fill_classes):
    # the thirtieth round's hash holds
    unfilled = SurfaceParams(point_fill_classes=())
    assert (
        Config(
            DetectParams(surface=unfilled, texture=near_off, appearance=any_holes)
        ).results_hash()
        == "d4fdd1d909361d52"
    )
    # every older hash below was made before the points' fill, the near layer, the holes'
    # roles and the see-through test's floor existed: built without them

    def unfilled_detect(**kw):
        appearance = kw.pop("appearance", any_holes)
        if appearance.hole_classes:
            appearance = dataclasses.replace(appearance, hole_classes=())
        texture = kw.pop("texture", near_off)
        if texture.near_layer_m or texture.see_through_colour_blur_px:
            texture = dataclasses.replace(texture, near_layer_m=0.0, see_through_colour_blur_px=0.0)
        return DetectParams(
            **{"surface": unfilled, "appearance": appearance, "texture": texture, **kw}
        )

    # the ground's colours not checked (the thirtieth round's appearance.ground_classes off):
    # the twenty-eighth round's hash holds, and with it every earlier one below
    inventory = AppearanceParams(ground_classes=(), hue_classes=(), dark_grey=False)
    assert Config(unfilled_detect(appearance=inventory)).results_hash() == "50c1033411893261"
    # the regions not located: the twenty-sixth round's hash holds
    unlocated = LocateParams(enabled=False)
    assert (
        Config(unfilled_detect(appearance=inventory, locate=unlocated)).results_hash()
        == "41d92911d6fdb382"
    )
    # the old vehicles' changed pixels not cut apart: the twenty-fifth round's hash holds,
    # and with it every earlier one below (a region's depth is not in them: off below)
    whole = RefineParams(apart_classes=())
    assert (
        Config(unfilled_detect(appearance=inventory, refine=whole, locate=unlocated)).results_hash()
        == "5f58a3c42a72f9a6"
    )
    # the twenty-fifth round's registration shifts off: the twenty-fourth round's hash holds
    unaligned = CorrelateParams(align_shift_px=0.0)
    assert (
        Config(
            unfilled_detect(
                appearance=inventory, refine=whole, locate=unlocated, correlate=unaligned
            )
        ).results_hash()
        == "27e71fcf2b40181e"
    )
    reach_only = CorrelateParams(silhouette_edge_threshold=0.0, align_shift_px=0.0)
    assert (
        Config(
            unfilled_detect(
                appearance=inventory, refine=whole, locate=unlocated, correlate=reach_only
            )
        ).results_hash()
        == "029b331307b07b3f"
    )
    no_band = CorrelateParams(silhouette_margin_m=0.0)  # then the outline changes nothing
    assert (
        Config(
            unfilled_detect(appearance=inventory, refine=whole, locate=unlocated, correlate=no_band)
        ).results_hash()
        == Config(
            unfilled_detect(
                appearance=inventory,
                refine=whole,
                locate=unlocated,
                correlate=dataclasses.replace(no_band, silhouette_edge_threshold=0.0),
            )
        ).results_hash()
    )
    # the earlier rounds' hashes hold with the band as they had it (its reach alone)
    ungated = CorrelateParams(
        second_smallest_gate=0.0, silhouette_edge_threshold=0.0, align_shift_px=0.0
    )
    assert (
        Config(
            unfilled_detect(appearance=inventory, refine=whole, locate=unlocated, correlate=ungated)
        ).results_hash()
        == "1be77a783281f300"
    )
    # eq. 5's minimum everywhere (the paper): the nineteenth round's hash holds
    minimum = CorrelateParams(
        second_smallest=False, silhouette_edge_threshold=0.0, align_shift_px=0.0
    )
    assert (
        Config(
            unfilled_detect(appearance=inventory, refine=whole, locate=unlocated, correlate=minimum)
        ).results_hash()
        == "0068d660689c1b69"
    )
    see_through_off = TextureParams(see_through_classes=())
    nineteenth_off = unfilled_detect(
        appearance=inventory,
        refine=whole,
        locate=unlocated,
        correlate=minimum,
        texture=see_through_off,
    )
    assert Config(nineteenth_off).results_hash() == "d6f5f4c2c16f882a"
    # a switch added off keeps the hash; on, it changes it
    nearer = CorrelateParams(
        nearer_weight=1.0,
        second_smallest=False,
        silhouette_edge_threshold=0.0,
        align_shift_px=0.0,
    )
    nearer_on = Config(
        unfilled_detect(appearance=inventory, refine=whole, locate=unlocated, correlate=nearer)
    )
    # with the test's version 2 (neighbours on both sides, 2026-11-30); 27bc9c9b9acee9ea before
    assert nearer_on.results_hash() == "a74eabbf45ce327a"
    blurred = Config(
        unfilled_detect(
            appearance=inventory, refine=whole, locate=unlocated, texture=TextureParams(blur_px=1.5)
        )
    )
    assert blurred.results_hash() not in (base.results_hash(), nearer_on.results_hash())
    floored = Config(
        unfilled_detect(
            appearance=inventory,
            refine=whole,
            locate=unlocated,
            correlate=CorrelateParams(registration_floor_px=2.0),
        )
    )
    assert floored.results_hash() not in (base.results_hash(), nearer_on.results_hash())
    log_transfer = Config(
        unfilled_detect(appearance=AppearanceParams(transfer="log", ground_classes=()))
    )
    assert log_transfer.results_hash() not in (base.results_hash(), nearer_on.results_hash())
    reach_colour = Config(
        unfilled_detect(appearance=inventory, zbuffer=ZBufferParams(reach_colour=True))
    )
    assert reach_colour.results_hash() not in (base.results_hash(), nearer_on.results_hash())
    # the surface and z-buffer of the sixteenth round's defaults (with today's rules of the
    # inferred roles, whose version is in the hash)
    dense_surface = SurfaceParams(
        point_fill_classes=(),
        spacing_edge_factor=0.0,
        spacing_edge_min_spacing_m=0.0,
        spacing_edge_same_role=False,
    )
    sixteenth = unfilled_detect(
        appearance=inventory,
        refine=whole,
        locate=unlocated,
        surface=dense_surface,
        zbuffer=ZBufferParams(reach_colour=True),
        texture=see_through_off,
        correlate=minimum,
    )
    assert Config(sixteenth).results_hash() == "23428be1e41784c0"
    # without inference the rules' version is left out, and without the foreshortening test
    # its setting: the hash of the settings before both (7fee81a419188dbe with infer off)
    before = dataclasses.replace(
        sixteenth,
        classes=ClassMap(infer="off"),
        texture=TextureParams(min_foreshortening=0.0, see_through_classes=(), near_layer_m=0.0),
    )
    assert Config(before).results_hash() == "5d2d95da524a50c4"
    texture_off = Config(
        unfilled_detect(appearance=inventory, texture=TextureParams(enabled=False))
    )
    assert texture_off.results_hash() != base.results_hash()
    city_codes = Config(unfilled_detect(appearance=inventory, classes=ClassMap(pole=(15,))))
    assert city_codes.results_hash() != base.results_hash()
    # speed only: the same results
    assert base.replace_run(batch_size=9, workers=5).results_hash() == base.results_hash()
    changed = [
        Config(unfilled_detect(appearance=inventory, correlate=CorrelateParams(n_neighbours=2))),
        base.replace_run(min_region_fraction=0.01),
        base.replace_run(write_overlays=False),
        base.replace_run(segments=SegmentParams(max_gap_m=10.0)),
        Config(unfilled_detect(appearance=inventory, graphcut=GraphCutParams(beta=2.0))),
    ]
    hashes = {c.results_hash() for c in changed}
    assert len(hashes) == len(changed) and base.results_hash() not in hashes


def test_scale_px():
    assert scale_px(30, 4000) == 30
    assert scale_px(30, 2000) == 15
    assert scale_px(30, 10) == 1.0
