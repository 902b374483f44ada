"""No non-finite action leaves the controller; observations are checked at its boundary; envs refuse NaN."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from conftest import fit_normalizer
from ddp import build
from ddp.envs.chunked import ChunkedEnv
from ddp.envs.synthetic_reach import SyntheticReachEnv, SyntheticReachEnvConfig
from ddp.evaluate import make_chunked_env
from ddp.safety import HoldSpec, NonFiniteError, ObservationError


def _exp(tiny_recipe, **controller):
    tiny_recipe["controller"] = {"detector": {"name": "discrepancy", "tau": 1e9}, "tracker": None,
                                 "recovery": {"name": "none"}, **controller}
    e = build(tiny_recipe)
    fit_normalizer(e)
    return e


@pytest.fixture
def exp(tiny_recipe):
    return _exp(tiny_recipe)


@pytest.fixture
def exp_hold(tiny_recipe):
    return _exp(tiny_recipe, on_nonfinite="hold")


def observations(exp, chunk: int = 0, batch: int = 1) -> TensorDict:
    env = make_chunked_env(exp, seed=0)
    td = env.reset()
    env.close()
    td["chunk_index"] = torch.tensor([chunk])
    return td.expand(batch).clone() if batch > 1 else td


def poison(td, key, value=float("nan"), env=None):
    x = td[key]
    if env is None:
        x[..., 0, -1, 0] = value  # one coordinate of the last point of the oldest frame
    else:
        x[env, -1].view(-1)[0] = value
    return td


@pytest.mark.parametrize("key", ["point_cloud", "agent_pos"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_observation_without_forecast_raises_one_line(exp, key, value):
    ctrl = exp.make_controller()
    td = observations(exp)
    td[key].view(-1)[5] = value
    with pytest.raises(NonFiniteError) as err:
        ctrl(td)
    msg = str(err.value)
    assert "\n" not in msg and "environment 0, chunk 0" in msg and "on_nonfinite" in msg


@pytest.mark.parametrize("key", ["point_cloud", "agent_pos"])
def test_nonfinite_observation_holds_when_the_recipe_says_so(exp_hold, key):
    ctrl = exp_hold.make_controller()
    td = observations(exp_hold)
    td[key].view(-1)[3] = float("nan")
    out = ctrl(td)
    assert out["ddp", "held"].item() and out["ddp", "mode"].item() == 1  # counted as OOD
    assert torch.equal(out["action"], torch.zeros(8, 4))  # synthetic_reach: every dim a delta
    assert torch.isinf(out["ddp", "discrepancy"]).all() and torch.equal(out["ee_shift"], torch.zeros(3))


@pytest.mark.parametrize("detector", [None, {"name": "never"}, {"name": "substitution", "p": 0.0}])
def test_nonfinite_observation_with_a_forecast_imagines_instead(exp, detector):
    ctrl = exp.make_controller(detector=detector)  # whatever the detector says, NaN input is OOD
    ctrl(observations(exp, chunk=0))  # a finite cycle: the world model's forecast exists
    td = poison(observations(exp, chunk=1), "point_cloud")
    out = ctrl(td)
    assert out["ddp", "mode"].item() == 1 and out["ddp", "imagined"].item() and not out["ddp", "held"].item()
    assert torch.isfinite(out["action"]).all()
    # the next finite observation re-checks D_R-I (tau is huge: back to reality)
    out = ctrl(observations(exp, chunk=2))
    assert out["ddp", "mode"].item() == 0 and not out["ddp", "imagined"].item()


def test_one_poisoned_env_does_not_touch_the_others(exp_hold):
    ctrl = exp_hold.make_controller()
    clean = ctrl(observations(exp_hold, batch=2))["action"].clone()
    ctrl.reset()
    out = ctrl(poison(observations(exp_hold, batch=2), "point_cloud", env=1))
    assert out["ddp", "held"].tolist() == [False, True]
    assert torch.equal(out["action"][0], clean[0]) and torch.equal(out["action"][1], torch.zeros(8, 4))


def test_nan_weights_are_refused_and_never_reach_an_action(exp, exp_hold):
    with torch.no_grad():
        exp.model.policy_net.parameters().__next__().fill_(float("nan"))
    with pytest.raises(NonFiniteError, match="holds NaN or inf"):
        exp.make_controller()
    ctrl = exp_hold.make_controller()  # weights that turn NaN after the controller was built
    with torch.no_grad():
        for p in exp_hold.model.parameters():
            p.fill_(float("nan"))
    out = ctrl(observations(exp_hold))
    assert out["ddp", "held"].item() and torch.isfinite(out["action"]).all()
    assert out["ddp", "mode"].item() == 1


def test_nonfinite_policy_output_is_held(exp_hold, monkeypatch):
    ctrl = exp_hold.make_controller()
    ctrl(observations(exp_hold))
    monkeypatch.setattr(exp_hold.model, "sample_actions", lambda c, generator=None: torch.full((c.shape[0], 16, 4), math.nan))
    out = ctrl(observations(exp_hold, chunk=1))
    assert out["ddp", "held"].item() and torch.equal(out["action"], torch.zeros(8, 4))
    # the held chunk is what executes: the next cycle has its forecast, a D_R-I to score
    monkeypatch.undo()
    out = ctrl(observations(exp_hold, chunk=2))
    assert not out["ddp", "held"].item() and torch.isfinite(out["ddp", "discrepancy"]).all()


def test_nonfinite_observation_held_without_forecast_makes_none(exp_hold):
    """Held for a non-finite observation with nothing imagined: its latents are no state to forecast from."""
    ctrl = exp_hold.make_controller()
    ctrl(poison(observations(exp_hold), "point_cloud"))
    out = ctrl(observations(exp_hold, chunk=1))
    assert torch.isnan(out["ddp", "discrepancy"]).all()


def test_hold_repeats_absolute_dims_and_uses_reset_values():
    spec = HoldSpec(absolute=(3,), reset={3: -1.0})
    assert spec.action(None, 4, 2).tolist() == [[0, 0, 0, -1.0]] * 2
    assert spec.action(torch.tensor([0.5, 0.5, 0.5, 0.7]), 4, 1).tolist() == [[0, 0, 0, pytest.approx(0.7)]]
    assert HoldSpec(absolute="all").action(None, 3, 1) is None  # cannot hold before a first action
    assert HoldSpec(absolute="all").action(torch.ones(3), 3, 1).tolist() == [[1.0, 1.0, 1.0]]


def test_a_controller_built_in_code_holds_only_as_told(exp):
    """No default hold: holding every dim at 0 would open a Franka gripper (its dim is absolute)."""
    from ddp.inference import DDPController

    det = exp.make_controller().detector
    with pytest.raises(ValueError, match="on_nonfinite='hold' needs hold="):
        DDPController(exp.model, detector=det, on_nonfinite="hold")
    DDPController(exp.model, detector=det, on_nonfinite="hold", hold=HoldSpec(absolute=(3,), reset={3: -1.0}))
    # a spec for another action space (a 7-d arm's gripper dim 6 on this 4-d one) held that command at 0
    with pytest.raises(ValueError, match="HoldSpec: absolute action dimension 6 is outside the 4 dimensions"):
        DDPController(exp.model, detector=det, on_nonfinite="hold", hold=HoldSpec(absolute=(6,), reset={6: -1.0}))


def test_hold_needs_an_env_that_declares_it(tiny_recipe):
    from ddp.errors import RecipeError

    tiny_recipe["controller"] = {"on_nonfinite": "hold", "tracker": None}
    exp = build(tiny_recipe)
    exp.parts["env"].plugin.factory.action_hold  # synthetic_reach declares it
    del tiny_recipe["env"]
    with pytest.raises(RecipeError, match="controller.on_nonfinite: 'hold' needs"):
        build(tiny_recipe).make_controller()


# ---------------------------------------------------------------- observation checks (one line each)
@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda td: td.set("point_cloud", td["point_cloud"][:, :0]), "0 points"),
        (lambda td: td.set("agent_pos", td["agent_pos"][..., :7]), "agent_pos' has 7 features; the model expects 9"),
        (lambda td: td.del_("chunk_index"), "no 'chunk_index'"),
        (lambda td: td.del_("point_cloud"), "no 'point_cloud'"),
        (lambda td: td.set("point_cloud", td["point_cloud"][-1:]), "holds 1 step"),
        (lambda td: td.set("agent_pos", td["agent_pos"][-1:]), "holds 1 step"),
        (lambda td: td.set("point_cloud", td["point_cloud"][..., :2]), "2 channels per point"),
        (lambda td: td.set("point_cloud", td["point_cloud"].to(torch.complex64)), "must be a float or integer tensor"),
        (lambda td: td.set("agent_pos", td["agent_pos"] > 0), "'agent_pos' must be a float or integer tensor"),
        (lambda td: td.set("point_cloud", td["point_cloud"][0]), "must be .B, M, P, C."),
        (lambda td: td.set("chunk_index", torch.tensor([0, 1])), "one index per environment"),
        (lambda td: td.unsqueeze(0)[:0], "batch is empty"),
    ],
    ids=["no-points", "agent-pos-size", "no-chunk-index", "no-point-cloud", "one-pc-step", "one-pos-step",
         "two-channels", "complex", "bool", "pc-rank", "chunk-shape", "empty-batch"],
)
def test_bad_observations_give_one_line(exp, mutate, match):
    ctrl = exp.make_controller()
    td = mutate(observations(exp))
    with pytest.raises(ObservationError, match=match) as err:
        ctrl(td)
    assert "\n" not in str(err.value)


def test_float64_clouds_work_and_odd_shapes_warn_once(exp):
    ctrl = exp.make_controller()
    ref = ctrl(observations(exp))["action"].clone()
    ctrl.reset()
    td = observations(exp)
    td["point_cloud"], td["agent_pos"] = td["point_cloud"].double(), td["agent_pos"].double()
    assert torch.allclose(ctrl(td)["action"], ref, atol=1e-4)
    for dtype in (torch.int8, torch.int16, torch.int32, torch.uint8):  # integers are cast (int8 / int16 were refused)
        ctrl.reset()
        td = observations(exp)
        td["point_cloud"] = td["point_cloud"].to(dtype)
        assert torch.isfinite(ctrl(td)["action"]).all()
    td = observations(exp)
    td["point_cloud"] = torch.cat([td["point_cloud"], td["point_cloud"][:, :5]], 1)  # 69 points, 4 channels
    td["point_cloud"] = torch.cat([td["point_cloud"], torch.zeros(*td["point_cloud"].shape[:-1], 1)], -1)
    with pytest.warns(UserWarning) as rec:
        ctrl(td.clone())
        ctrl(td.clone())
    messages = [str(w.message) for w in rec]
    assert sum("69 points" in m for m in messages) == 1 and sum("4 channels" in m for m in messages) == 1


# ---------------------------------------------------------------- envs refuse non-finite actions
def test_envs_refuse_nonfinite_actions_and_shifts():
    base = SyntheticReachEnv(SyntheticReachEnvConfig(num_points=32), seed=0)
    base.reset()
    with pytest.raises(NonFiniteError, match="synthetic_reach env: refused a non-finite action"):
        base.step(TensorDict({"action": torch.tensor([0.0, math.nan, 0.0, 0.0])}, []))
    with pytest.raises(NonFiniteError, match="end-effector shift"):
        base.shift_end_effector(np.array([0.0, np.inf, 0.0]))
    env = ChunkedEnv(base, action_steps=8, obs_steps=2)
    td = env.reset()
    steps = base._steps
    td["action"] = torch.zeros(8, 4)
    td["action"][7, 0] = math.nan  # the last action: nothing of the chunk may run
    td["ee_shift"] = torch.zeros(3)
    with pytest.raises(NonFiniteError, match="chunked env: refused a non-finite action chunk"):
        env.step(td)
    assert base._steps == steps
    td["action"] = torch.zeros(8, 4)
    td["ee_shift"] = torch.tensor([math.nan, 0.0, 0.0])
    with pytest.raises(NonFiniteError, match="end-effector shift"):
        env.step(td)


def test_chunked_env_reset_plays_the_seed_it_is_given_and_refuses_other_chunks():
    """reset(seed=7) played the next episode (the seed was dropped); a chunk of another length ran that many
    steps as one chunk (the render schedule then fed stale clouds)."""
    cfg = SyntheticReachEnvConfig(num_points=64, table_points=64, cube_points=48, gripper_points=16)
    env = ChunkedEnv(SyntheticReachEnv(cfg, seed=0), action_steps=8, obs_steps=2)
    direct = ChunkedEnv(SyntheticReachEnv(cfg, seed=7), action_steps=8, obs_steps=2)
    a, b = env.reset(seed=7), direct.reset()
    assert int(a["episode_seed"]) == 7 and torch.equal(a["point_cloud"], b["point_cloud"])
    with pytest.raises(TypeError, match="chunked env: reset\\(\\) takes seed=; got options"):
        env.reset(options=1)
    for steps in (3, 16):
        td = env.reset()
        td.set("action", torch.zeros(steps, 4))
        with pytest.raises(ValueError, match=f"an action chunk is \\[8, 4\\] .*; got shape \\[{steps}, 4\\]"):
            env.step(td)


def test_chunked_env_checks_the_whole_chunk_before_the_shift_and_refuses_an_ended_episode():
    """Only the chunk's length was checked before the end-effector shift ran: actions of the wrong width moved
    the end-effector, then were refused with no step run; a 1-D action was a bare IndexError; a step after
    done ran the shift and an action on the ended episode (the base env has no done guard)."""
    cfg = SyntheticReachEnvConfig(num_points=32, max_episode_steps=16)
    base = SyntheticReachEnv(cfg, seed=0)
    env = ChunkedEnv(base, action_steps=8, obs_steps=2)
    shift = torch.tensor([0.05, 0.0, 0.0])
    for action in (torch.zeros(8, 3), torch.zeros(8)):
        env.reset()
        with pytest.raises(ValueError, match=r"an action chunk is \[8, 4\]"):
            env.step(TensorDict({"action": action, "ee_shift": shift}, []))
        assert np.array_equal(base.ee_offset, np.zeros(3)) and base._steps == 0  # nothing moved
    with pytest.raises(ValueError, match=r"ee_shift is 3 numbers"):
        env.step(TensorDict({"action": torch.zeros(8, 4), "ee_shift": torch.zeros(2)}, []))
    td = env.reset()
    for _ in range(2):
        td = env.step(TensorDict({"action": torch.zeros(8, 4)}, []))["next"]
    assert bool(td["done"]) and base._steps == 16
    with pytest.raises(RuntimeError, match=r"the episode has ended \(done\); reset\(\) before the next step"):
        env.step(TensorDict({"action": torch.zeros(8, 4), "ee_shift": shift}, []))
    assert base._steps == 16 and np.array_equal(base.ee_offset, np.zeros(3))
    env.reset()
    env.step(TensorDict({"action": torch.zeros(8, 4)}, []))  # a reset clears it
    assert base._steps == 8


def test_env_schedules_the_episode_never_observes_and_negative_seeds_are_refused():
    base = dict(num_points=64, table_points=64, cube_points=48, gripper_points=16, max_episode_steps=48)
    with pytest.raises(ValueError, match="displacement_chunk 5 is first observed at step 48.*max_episode_steps > 48"):
        SyntheticReachEnvConfig(**base, displacement=True, displacement_chunk=5)
    SyntheticReachEnvConfig(**base, displacement=True, displacement_chunk=4)  # observed at 40, a chunk acts on it
    with pytest.raises(ValueError, match="occlusion_chunk 5 is first observed at step 48.*max_episode_steps > 48"):
        SyntheticReachEnvConfig(**base, occlusion_chunk=5)
    env = SyntheticReachEnv(SyntheticReachEnvConfig(**base), seed=0)
    with pytest.raises(ValueError, match="episode seeds must be >= 0; got -5"):  # -5 replayed episode 5
        env.reset(seed=-5)


def test_the_base_render_schedule_works_without_obs_every():
    """An adapter keeping the base _render_due on a config without obs_every / obs_history (the shared
    ObservationOptions has neither) failed at its first step: it renders every frame."""
    from ddp.envs.base import PointCloudEnv

    env = SyntheticReachEnv(SyntheticReachEnvConfig(num_points=64, table_points=64, cube_points=48,
                                                    gripper_points=16), seed=0)
    assert not hasattr(env.config, "obs_every")
    assert all(PointCloudEnv._render_due(env, t) for t in range(10))


def test_a_held_chunk_does_not_move_the_arm_by_a_tracking_shift(tiny_recipe):
    """A non-finite observation forces OOD and the tracker may see the displaced target then: the held chunk
    still sent its a^track (the arm moved 20 cm on a cycle the controller treated as a sensor fault). The shift
    now waits for the next cycle with a finite observation, and the recovery still undoes it."""
    from conftest import DELTA, displaced_exp

    exp = displaced_exp(tiny_recipe, on_nonfinite="hold")
    # the oracle detector re-decides every cycle; a sticky one that never fires keeps OOD only while the
    # taken-back shift waits (the sensor fault's re-check would otherwise return to reality untracked)
    for detector in ({"name": "oracle"}, {"name": "discrepancy", "tau": 1e9}):
        ctrl = exp.make_controller(imagine=False, detector=detector)
        env = make_chunked_env(exp, seed=0)
        ctrl.reset()
        td, held, shifts, offsets, modes = env.reset(), [], [], [], []
        for cycle in range(6):
            if cycle == 2:  # the first observation showing the move
                td = poison(td, "point_cloud")
            out = ctrl(td)
            held.append(bool(out["ddp", "held"]))
            shifts.append(out["ee_shift"].clone())
            modes.append(int(out["ddp", "mode"]))
            td = env.step(out.select("action", "ee_shift"))["next"]
            offsets.append(td["privileged", "ee_offset"].clone())
        env.close()
        assert held == [False, False, True, False, False, False], detector
        assert torch.equal(shifts[2], torch.zeros(3)) and torch.equal(offsets[2], torch.zeros(3))  # held: no motion
        assert torch.allclose(shifts[3], torch.tensor(DELTA)), detector  # tracked on the next finite cycle
        assert torch.allclose(shifts[4], -torch.tensor(DELTA))  # and undone at the subtask's end
        assert torch.allclose(offsets[4], torch.zeros(3), atol=1e-6) and modes[2:5] == [1, 1, 1], (detector, modes)


def test_an_env_factory_closes_the_base_env_when_the_chunked_env_is_refused(monkeypatch):
    """ChunkedEnv refusing its settings left the base env (a simulator, a robot connection) open."""
    from ddp.eval_runner import ChunkedEnvFactory

    closed = []
    monkeypatch.setattr(SyntheticReachEnv, "close", lambda self, **kw: closed.append(self))
    factory = ChunkedEnvFactory(plugin="synthetic_reach", config=SyntheticReachEnvConfig(num_points=32),
                                action_steps=1, obs_steps=2)  # fmt: skip
    with pytest.raises(ValueError, match="action_steps"):
        factory()
    assert len(closed) == 1
