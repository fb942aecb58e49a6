"""Parameter dataclasses: paper defaults, validation, YAML round trip."""

import dataclasses

import pytest

from streetcd.errors import InputError
from streetcd.params import (
    DetectParams,
    GraphCutParams,
    ZBufferParams,
    load_params,
    params_from_dict,
    params_to_dict,
    scale_px,
)


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
    assert load_params(default) == DetectParams()


def test_scale_px():
    assert scale_px(30, 4000) == 30
    assert scale_px(30, 2000) == 15
    assert scale_px(30, 10) == 1.0
