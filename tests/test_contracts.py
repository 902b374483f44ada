"""Each plugin kind's contract is checked at registration (classes) and at build (factories), in one line."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

import ddp
from conftest import fit_normalizer
from ddp import build, registry
from ddp.contracts import CONTRACTS, check, members
from ddp.errors import PluginError


@dataclass
class Empty:
    pass


def complete(kind: str) -> dict:
    """Class members satisfying ``kind``'s contract (so that one can be removed)."""
    attributes, methods = members(CONTRACTS[kind])
    body: dict = {a: None for a in attributes}
    signatures = {
        "shift_end_effector": lambda self, delta, *, safe_lift=0.0: delta,
        "recover": lambda self, offsets, displaced, target: (torch.zeros(3), displaced),
        "fired": lambda self, obs, chunk_index, subtask_chunks: False,
        "encode": lambda self, point_cloud, agent_pos: agent_pos,
        "load": lambda self: None,
        "loss": lambda self, model_fn, x0, *, generator=None: x0.sum(),
        "sample": lambda self, model_fn, noise, *, generator=None: noise,
        "forward": lambda self, td: td,
        "key": lambda self, role: role,
        "reset": lambda self: None,
    }
    for m in methods:
        body[m] = signatures.get(m, lambda self, *a, **k: None)
    return body


@pytest.mark.parametrize("kind", sorted(CONTRACTS))
def test_a_complete_class_registers_and_each_missing_member_is_named(kind):
    name = f"contract_test_{kind}"
    cls = type("Complete", (), complete(kind))
    try:
        registry.register(kind, name, config=Empty)(cls)
    finally:
        registry.unregister(kind, name)
    attributes, methods = members(CONTRACTS[kind])
    for member in methods:  # a class lacking a method is refused at registration
        body = complete(kind)
        del body[member]
        incomplete = type(f"Without_{member}", (), body)
        with pytest.raises(PluginError) as err:
            registry.register(kind, name, config=Empty)(incomplete)
        msg = str(err.value)
        assert f"{kind} '{name}'" in msg and f"'{member}()'" in msg and "\n" not in msg
        assert name not in registry._REGISTRY[kind]
    for member in attributes:  # attributes may come from __init__: the built part is checked
        body = complete(kind)
        del body[member]
        incomplete = type(f"Without_{member}", (), body)
        try:
            plugin = registry.register(kind, name, config=Empty)(incomplete)
            with pytest.raises(PluginError, match=rf"{kind} '{name}' .*lacks the attribute '{member}'"):
                check(kind, plugin(), name=name)
        finally:
            registry.unregister(kind, name)


@pytest.mark.parametrize(
    "kind, method, bad",
    [
        ("env", "shift_end_effector", lambda self, delta: delta),  # no safe_lift keyword
        ("recovery", "recover", lambda self, offsets: offsets),  # too few arguments
        ("trigger", "fired", lambda self, obs, chunk_index, subtask_chunks, extra: False),  # a required extra
        ("scheduler", "sample", lambda self, model_fn, noise: noise),  # no generator keyword
        ("detector", "forward", lambda self: None),  # cannot take the tensordict
        ("detector", "reset", lambda self, hard: None),  # a required argument core never passes
        ("tracker", "key", lambda self: None),  # cannot take the role
    ],
)
def test_signatures_that_cannot_take_cores_call_are_refused(kind, method, bad):
    body = complete(kind)
    body[method] = bad
    with pytest.raises(PluginError, match=rf"{method}\(\) must accept"):
        registry.register(kind, "contract_sig_test", config=Empty)(type("Bad", (), body))


def test_builtin_parts_satisfy_their_contracts():
    for kind in CONTRACTS:
        assert registry.plugins(kind), kind  # registering them checked each one


def test_a_factory_function_is_checked_when_the_recipe_builds_it(tiny_recipe):
    @ddp.register("detector", "half_detector", config=Empty)
    def half_detector(config):
        """A factory returning an object without in_keys / out_keys / sticky / needs_discrepancy."""
        return torch.nn.Identity()

    try:
        tiny_recipe["controller"] = {"detector": {"name": "half_detector"}, "tracker": None}
        exp = build(tiny_recipe)
        with pytest.raises(PluginError, match="detector 'half_detector' .* lacks the attribute 'in_keys'"):
            exp.make_controller()
    finally:
        registry.unregister("detector", "half_detector")


def test_an_env_factory_function_is_checked_wherever_an_env_is_made(tiny_recipe):
    """Envs were made by calling the factory directly: one without shift_end_effector failed at the first
    tracking shift, mid-evaluation, with an AttributeError."""
    from ddp.envs.synthetic_reach import SyntheticReachEnv, SyntheticReachEnvConfig
    from ddp.evaluate import make_chunked_env

    made = []

    @ddp.register("env", "half_env", config=SyntheticReachEnvConfig)
    def half_env(config, seed=None):
        env = SyntheticReachEnv(config, seed=seed)
        env.shift_end_effector = None  # not callable: the contract's method is missing
        close, env.closed = env.close, False

        def recorded_close(*args, **kwargs):
            env.closed = True
            return close(*args, **kwargs)

        env.close = recorded_close
        made.append(env)
        return env

    try:
        tiny_recipe["env"] = {**tiny_recipe["env"], "name": "half_env"}
        exp = build(tiny_recipe)
        for make in (lambda: exp.make_env(seed=0), lambda: make_chunked_env(exp, seed=0)):
            with pytest.raises(PluginError, match="env 'half_env' .* lacks the method 'shift_end_effector\\(\\)'"):
                make()
            assert made[-1].closed  # the refused env is closed (its renderer, a robot's connection)
    finally:
        registry.unregister("env", "half_env")


def test_the_controller_reads_renamed_detector_and_tracker_keys(tiny_recipe):
    """set_keys renames are honoured: the controller asks the part for its key, it does not assume one."""
    tiny_recipe["env"].update(displacement=True, displacement_chunk=1, displacement_delta=[0.2, 0.0, 0.0],
                              max_episode_steps=32)
    tiny_recipe["controller"] = {"detector": {"name": "oracle"}, "tracker": {"name": "oracle"},
                                 "recovery": {"name": "none"}}
    exp = build(tiny_recipe)
    fit_normalizer(exp)
    from ddp.evaluate import make_chunked_env

    ctrl = exp.make_controller()
    ctrl.detector.set_keys(ood=("mine", "is_ood"))
    ctrl.tracker.set_keys(offsets=("mine", "moved"))
    env = make_chunked_env(exp, seed=0)
    r = env.rollout(4, ctrl, break_when_any_done=False)
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1]  # the move (chunk 1) is seen from cycle 2
    assert torch.allclose(r["ee_shift"][2], torch.tensor([0.2, 0.0, 0.0]))
    assert ("mine", "is_ood") in r.keys(True) and ("ddp", "ood") not in r.keys(True)


def test_an_encoder_written_before_point_dim_still_builds(tiny_recipe):
    """Encoders receive point_dim when their factory takes it; an older one without it still builds."""
    from ddp.encoders.dp3 import DP3Encoder, DP3EncoderConfig

    @ddp.register("encoder", "old_encoder", config=DP3EncoderConfig)
    class OldEncoder(DP3Encoder):
        def __init__(self, config, *, agent_pos_dim):
            super().__init__(config, agent_pos_dim=agent_pos_dim)

    try:
        tiny_recipe["encoder"] = {"name": "old_encoder"}
        assert build(tiny_recipe).model.encoder.out_dim == 128
    finally:
        registry.unregister("encoder", "old_encoder")
