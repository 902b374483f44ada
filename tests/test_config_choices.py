"""``ddp.config.check_choices``: configs built in Python reject a value their ``Literal`` annotation does not admit."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import pytest

from ddp.config import check_choices


@dataclass
class _Cfg:
    mode: Literal["fast", "slow"] = "fast"
    level: Literal[1, 2] | None = None
    name: str = "free text"

    def __post_init__(self):
        check_choices(self, "part.")


def test_valid_values_pass_and_none_only_where_annotated():
    _Cfg()
    _Cfg(mode="slow", level=2, name="anything")
    with pytest.raises(ValueError, match=r"^part\.mode must be one of 'fast', 'slow'; got None$"):
        _Cfg(mode=None)


def test_a_wrong_value_names_the_field_and_the_closest_choice():
    with pytest.raises(ValueError, match=r"^part\.mode must be one of 'fast', 'slow'; got 'fats'; did you mean 'fast'\?$"):
        _Cfg(mode="fats")
    with pytest.raises(ValueError, match=r"^part\.level must be one of 1, 2, None; got 3$"):
        _Cfg(level=3)


def test_library_configs_use_it():
    from ddp.encoders.dp3 import DP3EncoderConfig
    from ddp.envs.disturbances import Displacement

    with pytest.raises(ValueError, match=r"^pool_backward must be one of .*; did you mean 'winners'\?$"):
        DP3EncoderConfig(pool_backward="winner")
    with pytest.raises(ValueError, match=r"^final_norm must be one of 'layernorm', 'none'; got 'batchnorm'"):
        DP3EncoderConfig(final_norm="batchnorm")
    with pytest.raises(ValueError, match=r"^Displacement\.tracking must be one of .*'two_stage'\?$"):
        Displacement(("obj",), (0.0, 0.0, 0.0), chunk=1, tracking="two")


@dataclass
class _Sub(_Cfg):
    """A subclass whose base's __post_init__ does the check: the subclass's own choices count too."""

    extra: Literal["x"] | Literal["y"] | None = None


def test_a_subclass_and_a_union_of_literals_are_checked():
    _Sub(extra="y")
    _Sub(extra=None)
    with pytest.raises(ValueError, match=r"^part\.extra must be one of 'x', 'y', None; got 'z'"):
        _Sub(extra="z")


def test_env_and_robot_configs_use_it():
    from ddp.envs.disturbances import Occlusion
    from ddp.envs.franka.real import RealBackendConfig

    with pytest.raises(ValueError, match=r"^env\.real\.motion_wait must be one of 'period', 'reached'; got 'reach'"):
        RealBackendConfig(motion_wait="reach")
    from ddp.envs.franka.env import FrankaEnvConfig

    with pytest.raises(ValueError, match=r"^backend must be one of 'sim', 'real'; got 'sm'; did you mean 'sim'\?$"):
        FrankaEnvConfig(backend="sm")  # checked by the shared observation options
    with pytest.raises(ValueError, match=r"^Occlusion\.mode must be one of 'zeros', 'drop', 'noise'; got 'zero'"):
        Occlusion(chunk=1, mode="zero")
