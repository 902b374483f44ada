"""Controller branches of Algorithm 2 that the end-to-end tests do not pin down, each on the synthetic env.

The re-check of D_R-I after a recovery (sticky detectors), the per-subtask triggers (timer, gripper
closure), the oracle snap-back at a fixed chunk, ``controller.track: false``, ``controller.safe_lift``
and the ``ood_base`` protocol. The untrained tiny model's actions are arbitrary: only the controller's
decisions (mode, subtask, ee_shift) and what the env executes are checked.
"""

import numpy as np
import pytest
import torch

from conftest import DELTA, displaced_exp
from ddp.evaluate import env_overrides, make_chunked_env
from ddp.protocols.base import get_protocol

CHUNKS = 8  # max_episode_steps 64 / action_steps 8
ZERO = torch.zeros(3)


make_exp = displaced_exp  # the tiny recipe on the displaced synthetic env, normaliser fitted


def rollout(exp, policy, env=None, **env_over):
    env = env if env is not None else make_chunked_env(exp, seed=0, overrides=env_over)
    ctrl = getattr(policy, "ctrl", policy)
    ctrl.reset()
    return env.rollout(CHUNKS, policy, break_when_any_done=False)


def shifts(r):
    return [[round(float(x), 6) for x in row] for row in r["ee_shift"]]


# --------------------------------------------------------------------------- 1. re-check after recovery
class ScriptedStickyDetector(torch.nn.Module):
    """A sticky detector (the D_R-I contract: once OOD, only a recovery + re-check ends it) whose
    verdict is scripted per chunk index: OOD exactly at the chunks in ``ood_at``."""

    sticky = True
    needs_discrepancy = False

    def __init__(self, ood_at):
        super().__init__()
        self.ood_at = set(ood_at)
        self.seen = []

    def key(self, role):
        return ("ddp", role)

    def forward(self, td):
        chunk = td.get("chunk_index").reshape(-1).tolist()
        self.seen += chunk
        td.set(("ddp", "ood"), torch.tensor([c in self.ood_at for c in chunk]))
        return td

    def reset(self):
        self.seen = []


def test_sticky_detector_returns_to_reality_only_at_the_recheck_after_recovery(tiny_recipe):
    exp = make_exp(tiny_recipe)  # subtask 0 (target 0) ends at chunk 4: recovery there
    ctrl = exp.make_controller()
    # OOD seen at chunk 2 only: sticky, so not-OOD at chunks 3-4 does not end OOD mode; the recovery at
    # chunk 4 arms a re-check on the first observation after it (chunk 5), where the detector says ID
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    r = rollout(exp, ctrl)
    assert ctrl.detector.seen == list(range(CHUNKS))
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 0, 0, 0]
    assert r["ddp", "imagined"].tolist()[2:5] == [True] * 3 and not r["ddp", "imagined"][5:].any()
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]  # track, then recover
    assert r["ddp", "subtask"].tolist()[4] == 1

    # the detector still says OOD at the re-check (chunk 5): OOD mode stays, and stays for good (one
    # re-check per recovery), although it says ID at chunks 6-7
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 1]
    assert r["ddp", "imagined"][2:].all()

    # without a recovery (subtask never ends) there is no re-check: OOD mode holds to the episode's end
    ctrl = exp.make_controller()
    ctrl.subtasks[0].trigger = None
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 1]


def test_resume_after_recovery_returns_to_reality_once_every_displaced_target_is_back(tiny_recipe):
    # the detector still says OOD at the re-check (chunk 5), as D_R-I does where a displaced object no
    # subtask targets stays where it was moved: with resume_after_recovery the controller returns anyway
    exp = make_exp(tiny_recipe, resume_after_recovery=True)
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 0, 0, 0]
    assert not r["ddp", "imagined"][5:].any()
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]

    # the detector goes on saying OOD (the scene stays changed): the tracker sees no displacement beyond the
    # one accepted at the resume, so the controller stays in reality
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5, 6, 7})
    assert rollout(exp, ctrl)["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 0, 0, 0]

    # nothing recovered (the subtask never ends): OOD mode holds, as without the option
    ctrl = exp.make_controller()
    ctrl.subtasks[0].trigger = None
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5})
    assert rollout(exp, ctrl)["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 1]


def test_recheck_until_id_keeps_rechecking_once_nothing_is_left_to_recover(tiny_recipe):
    # the re-check after the recovery (chunk 5) still says OOD; D_R-I falls below tau from chunk 6. The paper's
    # single re-check keeps OOD mode to the end; recheck_until_id returns at the first ID verdict
    exp = make_exp(tiny_recipe)
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5})
    assert rollout(exp, ctrl)["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 1]
    ctrl = make_exp(tiny_recipe, recheck_until_id=True).make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2, 5, 6})
    assert rollout(exp, ctrl)["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 0]

    # a displaced object not yet recovered (a later subtask's target) stops the repeated re-checks; one no
    # subtask targets (coffee-pull's machine) never will be recovered, so it does not
    from ddp.inference import EnvState, Subtask

    t, f = True, False
    ctrl.subtasks = [Subtask(target=0, trigger=None), Subtask(target=1, trigger=None)]
    assert ctrl._left_to_recover(EnvState(displaced=torch.tensor([t, t]), recovered=torch.tensor([t, f])))
    assert not ctrl._left_to_recover(EnvState(displaced=torch.tensor([t, f]), recovered=torch.tensor([t, f])))
    assert not ctrl._left_to_recover(EnvState())  # no tracker: nothing was ever followed
    ctrl.subtasks = [Subtask(target=0, trigger=None), Subtask(target=None, trigger=None)]
    assert not ctrl._left_to_recover(EnvState(displaced=torch.tensor([t, t]), recovered=torch.tensor([t, f])))


def test_targets_recovered_ignores_displaced_objects_no_subtask_targets(tiny_recipe):
    from ddp.inference import EnvState, Subtask

    ctrl = make_exp(tiny_recipe).make_controller()
    t, f = True, False
    state = EnvState(displaced=torch.tensor([t, t]), recovered=torch.tensor([t, f]))
    ctrl.subtasks = [Subtask(target=0, trigger=None), Subtask(target=None, trigger=None)]
    assert ctrl._targets_recovered(state)  # object 1 (coffee-pull's machine) is scenery
    ctrl.subtasks = [Subtask(target=0, trigger=None), Subtask(target=1, trigger=None)]
    assert not ctrl._targets_recovered(state)  # object 1 is still to be dealt with
    assert not ctrl._targets_recovered(EnvState(displaced=torch.tensor([t, f]), recovered=torch.tensor([f, f])))

    # after the resume, only a displacement beyond the accepted offsets counts as a new OOD event
    state.accepted = torch.tensor([[0.0, 0.0, 0.0], [-0.2, 0.0, 0.0]])
    same, moved = torch.tensor([[[0.0, 0.0, 0.0], [-0.19, 0.0, 0.0]]]), torch.tensor([[[0.0, 0.1, 0.0], [-0.2, 0.0, 0.0]]])
    assert ctrl._accepted_scene(state, same, 0) and not ctrl._accepted_scene(state, moved, 0)
    assert not ctrl._accepted_scene(EnvState(), same, 0) and not ctrl._accepted_scene(state, None, 0)
    # an object the tracker cannot see (zero offset: hidden behind the arm, or carried) is no new event
    hidden = torch.zeros(1, 2, 3)
    assert ctrl._accepted_scene(state, hidden, 0)
    # accepting a scene keeps, for an object not seen at that moment, the offset it was tracked at, so that
    # its reappearance there is no new event either
    state.offsets = torch.tensor([[0.0, 0.0, 0.0], [-0.2, 0.0, 0.0]])
    accepted = ctrl._scene_to_accept(state, hidden, hidden.norm(dim=-1) > 0, 0)
    assert torch.equal(accepted, state.offsets) and ctrl._scene_to_accept(state, None, None, 0) is None
    # a tracker that sees the object back at its place (visible, offset 0): that is the scene accepted
    assert torch.equal(ctrl._scene_to_accept(state, hidden, torch.ones(1, 2, dtype=torch.bool), 0), hidden[0])
    state.accepted = accepted
    assert ctrl._accepted_scene(state, torch.tensor([[[0.0, 0.0, 0.0], [-0.2, 0.0, 0.0]]]), 0)


# --------------------------------------------------------------------------- 2. per-subtask triggers
def test_timer_trigger_counts_chunks_from_the_subtask_start(tiny_recipe):
    exp = make_exp(tiny_recipe, subtasks=[
        {"target": 0, "trigger": {"name": "timer", "chunks": 2}},
        {"target": None, "trigger": {"name": "timer", "chunks": 3}},
        {"target": None},
    ])
    r = rollout(exp, exp.make_controller(detector={"name": "never"}), displacement=False)
    # subtask 0 ends at chunk 2 (2 chunks in it), subtask 1 three chunks later at chunk 5 (not at chunk 3,
    # which a trigger counting from the episode start would give)
    assert r["ddp", "subtask"].tolist() == [0, 0, 1, 1, 1, 2, 2, 2]


def test_timer_trigger_ends_the_subtask_with_its_recovery(tiny_recipe):
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "timer", "chunks": 6}}, {"target": None}])
    r = rollout(exp, exp.make_controller())
    assert r["ddp", "subtask"].tolist() == [0] * 6 + [1, 1]
    expected = [[0.0] * 3] * CHUNKS
    expected[2], expected[6] = DELTA, [-d for d in DELTA]  # tracked at OOD entry, recovered at the timer's end
    assert shifts(r) == expected


class CloseGripperFrom:
    """The controller, with the gripper command overridden: open before chunk ``chunk``, closed from it."""

    def __init__(self, ctrl, chunk):
        self.ctrl, self.chunk = ctrl, chunk

    def __call__(self, td):
        td = self.ctrl(td)
        closing = int(td["chunk_index"].reshape(-1)[0]) >= self.chunk
        td["action"][..., 3] = 1.0 if closing else -1.0
        return td


def test_gripper_closure_trigger_ends_the_subtask_when_the_fingers_close(tiny_recipe):
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "gripper_closure"}}, {"target": None}])
    # the gripper closes during chunk 2: the first observation showing it closed is chunk 3's
    r = rollout(exp, CloseGripperFrom(exp.make_controller(), chunk=2))
    width = (r["agent_pos"][:, -1, 3:6] - r["agent_pos"][:, -1, 6:9]).norm(dim=-1)
    assert (width[:3] > 0.045).all() and (width[3:] < 0.045).all()  # what the trigger reads
    assert r["ddp", "subtask"].tolist() == [0, 0, 0, 1, 1, 1, 1, 1]
    assert shifts(r)[2] == DELTA and shifts(r)[3] == [-d for d in DELTA]  # the subtask's recovery fires then
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 0, 0, 0, 0]  # the oracle sees the target recovered

    # a gripper that never closes never ends the subtask (and nothing is recovered)
    r = rollout(exp, CloseGripperFrom(exp.make_controller(), chunk=CHUNKS + 1))
    assert (r["ddp", "subtask"] == 0).all()
    assert all(s == [0.0] * 3 for i, s in enumerate(shifts(r)) if i != 2)


def test_gripper_closure_require_open_ends_a_second_grasp_subtask_only_on_its_own_closing(tiny_recipe):
    """Level-triggered, a second gripper subtask that starts while the first object is held ends one chunk
    later; with require_open it waits for the fingers to open and close again (the controller keeps the
    trigger's per-subtask memory)."""
    from ddp.triggers.gripper_closure import GripperClosureConfig, GripperClosureTrigger

    def subtasks(**options):
        return [{"target": 0, "trigger": {"name": "gripper_closure", **options}},
                {"target": None, "trigger": {"name": "gripper_closure", **options}}, {"target": None}]

    level = make_exp(tiny_recipe, subtasks=subtasks())
    r = rollout(level, CloseGripperFrom(level.make_controller(), chunk=2))
    assert r["ddp", "subtask"].tolist() == [0, 0, 0, 1, 2, 2, 2, 2]  # ended at once: still holding
    edge = make_exp(tiny_recipe, subtasks=subtasks(require_open=True))
    r = rollout(edge, CloseGripperFrom(edge.make_controller(), chunk=2))
    # the first subtask saw the fingers open (chunks 0-2), then closing; the second never sees them reopen
    assert r["ddp", "subtask"].tolist() == [0, 0, 0, 1, 1, 1, 1, 1]
    # the trigger alone: closed from the start reads nothing; open, then closed, fires
    trig, state = GripperClosureTrigger(GripperClosureConfig(require_open=True)), {}
    assert not trig.fired(_fingers([0.03]), 4, 0, state=state) and not trig.fired(_fingers([0.03]), 5, 1, state=state)
    assert not trig.fired(_fingers([0.08]), 6, 2, state=state) and trig.fired(_fingers([0.03]), 7, 3, state=state)
    with pytest.raises(ValueError, match="require_open needs the controller's per-subtask state"):
        trig.fired(_fingers([0.03]), 7, 3)


def _fingers(widths):
    """agent_pos frames [M, 9] (DP3's layout) whose finger distance is each of ``widths``."""
    pos = torch.zeros(len(widths), 9)
    pos[:, 3], pos[:, 6] = torch.tensor(widths) / 2, -torch.tensor(widths) / 2
    return {"agent_pos": pos}


def test_gripper_closure_settled_below_fires_on_a_grasp_wider_than_width_below():
    from ddp.triggers.gripper_closure import GripperClosureConfig, GripperClosureTrigger

    plain = GripperClosureTrigger(GripperClosureConfig())
    settled = GripperClosureTrigger(GripperClosureConfig(settled_below=0.09))
    holding_mug = _fingers([0.0562, 0.0560])  # MetaWorld coffee-pull: fingers stopped on the mug at 0.056 m
    assert not plain.fired(holding_mug, 8, 8)  # the plain width threshold never sees this grasp
    assert settled.fired(holding_mug, 8, 8)
    assert not settled.fired(_fingers([0.070, 0.062]), 8, 8)  # still closing: not yet a grasp
    assert not settled.fired(_fingers([0.100, 0.100]), 8, 8)  # open and still
    assert not settled.fired(holding_mug, 0, 0)  # min_chunks
    assert settled.fired(_fingers([0.050, 0.040]), 8, 8) and plain.fired(_fingers([0.050, 0.040]), 8, 8)
    assert not settled.fired(_fingers([0.056]), 8, 8)  # one frame: no motion to judge, width_below only
    for bad in (0.04, float("nan")):
        with pytest.raises(ValueError, match="settled_below"):
            GripperClosureConfig(settled_below=bad)
    with pytest.raises(ValueError, match="settle_tol"):
        GripperClosureConfig(settled_below=0.09, settle_tol=float("nan"))


def test_gripper_closure_empty_below_lets_a_missed_grasp_go_on_and_bad_settings_are_refused():
    from ddp.errors import RecipeError
    from ddp.recovery.target_specific import TargetSpecificConfig, TargetSpecificRecovery
    from ddp.triggers.gripper_closure import GripperClosureConfig, GripperClosureTrigger

    paper = GripperClosureTrigger(GripperClosureConfig(settled_below=0.09))
    missed = GripperClosureTrigger(GripperClosureConfig(settled_below=0.09, empty_below=0.035))
    on_air, on_puck = _fingers([0.031, 0.030]), _fingers([0.0452, 0.0450])  # MetaWorld: closed on nothing / a puck
    assert paper.fired(on_air, 8, 8) and not missed.fired(on_air, 8, 8)  # the missed grasp does not end the subtask
    assert paper.fired(on_puck, 8, 8) and missed.fired(on_puck, 8, 8)
    assert missed.fired(_fingers([0.0562, 0.0560]), 8, 8)  # the mug, settled
    for bad, match in ((dict(width_below=4.5), r"width_below must be in \(0, 0.5\] metres; got 4.5"),
                       (dict(width_below=float("nan")), "width_below must be in"),
                       (dict(empty_below=0.05), r"empty_below must be < width_below \(0.045\)"),
                       (dict(left=(3, 5)), r"left must be an agent_pos slice \[start, start \+ 3\).*got \[3, 5\]"),
                       (dict(right=(6,)), "right must be an agent_pos slice"),
                       (dict(min_chunks=-1), "min_chunks must be >= 0")):
        with pytest.raises(ValueError, match=match):
            GripperClosureConfig(**bad)
    with pytest.raises(RecipeError, match=r"controller.subtasks\[\*\].trigger: agent_pos has 4 dims; the "
                                          r"gripper_closure finger slices .* need 9"):
        paper.fired({"agent_pos": torch.zeros(2, 4)}, 8, 8)
    # recovery: objects it also moves back must exist
    with pytest.raises(ValueError, match=r"also_recovers must list object indices >= 0; got \[-1\]"):
        TargetSpecificConfig(also_recovers=[-1])
    rec = TargetSpecificRecovery(TargetSpecificConfig(also_recovers=[5]))
    with pytest.raises(RecipeError, match=r"controller.recovery.also_recovers: object 5 is not one of the 2 object\(s\)"):
        rec.recover(torch.ones(2, 3), torch.tensor([True, False]), 0)
    shift, recovered = TargetSpecificRecovery(TargetSpecificConfig(also_recovers=[1])).recover(
        torch.ones(2, 3), torch.tensor([True, False]), 0)
    assert recovered.tolist() == [True, True] and shift.tolist() == [-1.0] * 3


# --------------------------------------------------------------------------- 3. oracle snap-back
@pytest.mark.parametrize("trigger", [{"name": "chunk_index", "chunk": 3}, {"name": "timer", "chunks": 1}, None])
def test_oracle_snapback_recovers_at_its_fixed_chunk_whatever_the_triggers_say(tiny_recipe, trigger):
    exp = make_exp(tiny_recipe, recovery={"name": "oracle_snapback", "chunk": 6},
                   subtasks=[{"target": 0, "trigger": trigger}, {"target": None}])
    r = rollout(exp, exp.make_controller())
    expected = [[0.0] * 3] * CHUNKS
    expected[2], expected[6] = DELTA, [-d for d in DELTA]
    assert shifts(r) == expected
    assert r["ddp", "subtask"].tolist() == [0] * 6 + [1, 1]  # the fixed chunk ends one subtask, once
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 0]  # recovered at 6, seen so at 7
    offsets = r["next", "privileged", "ee_offset"]
    assert torch.allclose(offsets[5], torch.tensor(DELTA)) and torch.allclose(offsets[6], ZERO, atol=1e-6)


# --------------------------------------------------------------------------- 4. controller.track
def test_track_false_enters_ood_without_a_tracking_shift(tiny_recipe):
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0}])  # no subtask end: no recovery shift either
    r = rollout(exp, exp.make_controller(track=True))
    assert r["ddp", "mode"][2] == 1 and shifts(r)[2] == DELTA
    assert torch.allclose(r["next", "privileged", "ee_offset"][2], torch.tensor(DELTA))

    r = rollout(exp, exp.make_controller(track=False))
    assert r["ddp", "mode"].tolist() == [0, 0] + [1] * 6 and r["ddp", "imagined"][2:].all()
    assert (r["ee_shift"] == 0).all()
    assert torch.allclose(r["next", "privileged", "ee_offset"], torch.zeros(CHUNKS, 3))

    class LateTracker(torch.nn.Module):
        """Cannot see the object at the OOD entry (cycle 2); sees it from cycle 3 (the keep-tracking path)."""

        def __init__(self):
            super().__init__()
            self.calls = 0

        def forward(self, td):
            self.calls += 1
            offsets = td.get(("privileged", "displacement")).clone()
            if self.calls <= 3:
                offsets.zero_()
            td.set(("ddp", "offsets"), offsets)
            return td

        def reset(self):
            self.calls = 0

        def key(self, role):
            return ("ddp", role)

    # with a subtask end, track: false emits no recovery shift either (there is no tracking shift to undo),
    # although the object counts as recovered and D_R-I is re-checked
    exp2 = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 4}},
                                           {"target": None}])
    r = rollout(exp2, exp2.make_controller(track=False))
    assert (r["ee_shift"] == 0).all() and r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 0, 0, 0]
    assert torch.allclose(r["next", "privileged", "ee_offset"], torch.zeros(CHUNKS, 3))
    r = rollout(exp2, exp2.make_controller(track=True))
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]

    for track, late_shift in ((True, DELTA), (False, [0.0] * 3)):
        ctrl = exp.make_controller(track=track)
        ctrl.tracker = LateTracker()
        r = rollout(exp, ctrl)
        assert r["ddp", "mode"][2] == 1 and shifts(r)[2] == [0.0] * 3
        assert shifts(r)[3] == late_shift, track


class ScriptedTracker(torch.nn.Module):
    """Offsets [B, K, 3] of K objects: ``offsets`` from chunk ``from_chunk`` on, zero (not moved) before."""

    def __init__(self, offsets, from_chunk):
        super().__init__()
        self.offsets, self.from_chunk = torch.tensor(offsets), from_chunk

    def forward(self, td):
        chunk = td.get("chunk_index").reshape(-1)
        out = torch.zeros(chunk.shape[0], *self.offsets.shape)
        out[chunk >= self.from_chunk] = self.offsets
        td.set(("ddp", "offsets"), out)
        return td

    def reset(self):
        pass

    def key(self, role):
        return ("ddp", role)


def test_a_later_subtasks_target_moved_before_it_began_is_tracked_when_it_begins(tiny_recipe):
    """Two subtasks with two targets (Franka pour: the teapot, then the cup), the second target moved while
    the first subtask runs: its a^track comes when its subtask begins in OOD mode, so that its a^rec at
    the subtask's end undoes a shift that happened (the shifts of the episode sum to zero)."""
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 4}},
                                          {"target": 1, "trigger": {"name": "chunk_index", "chunk": 6}},
                                          {"target": None}])
    moved = [0.0, 0.1, 0.0]
    for track in (True, False):
        ctrl = exp.make_controller(track=track)
        ctrl.detector = ScriptedStickyDetector(ood_at={2})
        ctrl.tracker = ScriptedTracker([[0.0, 0.0, 0.0], moved], from_chunk=2)
        r = rollout(exp, ctrl)
        assert r["ddp", "subtask"].tolist() == [0, 0, 0, 0, 1, 1, 2, 2]
        # OOD from chunk 2 (object 1 moved; subtask 0's target did not: nothing to track yet, and no
        # recovery at its end, so no re-check); object 1's subtask begins at chunk 4, ends at chunk 6 with
        # its recovery and the re-check at chunk 7, where the detector says ID
        assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 0]
        expected = [[0.0] * 3 for _ in range(CHUNKS)]
        if track:
            expected[4], expected[6] = moved, [-d for d in moved]
        assert shifts(r) == expected
        assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


class PutBackTracker(ScriptedTracker):
    """Object 1 moved at chunk 2 and put back at chunk 3 (offset 0 from then on), every object in view:
    with ``visible`` its "object_visible" output says so, as the depth trackers' does."""

    def __init__(self, moved, visible: bool, carried: bool = False, after: float = 0.0):
        super().__init__([[0.0, 0.0, 0.0], moved], from_chunk=2)
        self.visible, self.carried, self.after = visible, carried, after

    def forward(self, td):
        td = super().forward(td)
        chunk = td.get("chunk_index").reshape(-1)
        td.get(("ddp", "offsets"))[chunk >= 3] = self.after  # (NaN: a measurement that failed)
        if self.visible:
            td.set(("ddp", "object_visible"), torch.ones(chunk.shape[0], 2, dtype=torch.bool))
            # carried: in the hand from chunk 3 on (its offset reads 0 there, as the depth trackers' does)
            td.set(("ddp", "object_carried"), (chunk >= 3)[:, None] & torch.tensor([False, self.carried]))
        return td

    def key(self, role):
        if role in ("visible", "carried") and not self.visible:
            raise KeyError(role)
        return {"visible": ("ddp", "object_visible"), "carried": ("ddp", "object_carried")}.get(role, ("ddp", role))


def test_a_target_seen_back_at_its_place_is_not_shifted_by_its_old_offset(tiny_recipe):
    """A later subtask's target moved while OOD and was put back before its subtask began: a depth tracker
    sees it (object_visible) at offset 0, but the controller took a zero offset for "cannot see it" and
    shifted the end-effector by the offset recorded when OOD began (and its recovery undid a wrong shift).
    A tracker without the visible role keeps that reading (the oracle's zero is no measurement of a hidden
    object either way)."""
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 4}},
                                          {"target": 1, "trigger": {"name": "chunk_index", "chunk": 6}},
                                          {"target": None}])
    moved = [0.0, 0.1, 0.0]
    # carried (in the hand, offset 0) is not "back at its place": the offset known before counts, as when hidden
    # and a non-finite offset is no measurement, whatever "visible" says
    for visible, carried, after, at_4 in ((True, False, 0.0, [0.0] * 3), (False, False, 0.0, moved),
                                          (True, True, 0.0, moved), (True, False, float("nan"), moved)):
        ctrl = exp.make_controller()
        ctrl.detector = ScriptedStickyDetector(ood_at={2})
        ctrl.tracker = PutBackTracker(moved, visible, carried, after)
        r = rollout(exp, ctrl)
        assert r["ddp", "subtask"].tolist() == [0, 0, 0, 0, 1, 1, 2, 2]
        assert shifts(r)[4] == at_4, (visible, carried, after)
        assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


def test_reality_does_not_resume_while_a_tracked_target_waits_for_its_recovery(tiny_recipe):
    """Both targets moved: subtask 0's recovery (chunk 4) is also where subtask 1 begins and its target is
    tracked. The re-check after that recovery (chunk 5) says ID, but the controller stays OOD until subtask
    1's recovery has undone its tracking shift (the episode's shifts sum to zero)."""
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 4}},
                                          {"target": 1, "trigger": {"name": "chunk_index", "chunk": 6}},
                                          {"target": None}])
    first, second = [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    ctrl.tracker = ScriptedTracker([first, second], from_chunk=2)
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist() == [0, 0, 1, 1, 1, 1, 1, 0]
    expected = [[0.0] * 3 for _ in range(CHUNKS)]
    expected[2], expected[4], expected[6] = first, [-0.1, 0.1, 0.0], [-d for d in second]
    assert shifts(r) == expected
    assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


def test_a_tracking_shift_cut_by_the_workspace_is_undone_as_executed(tiny_recipe):
    """The env clips the tracking shift at its workspace's edge (here x at +0.05 of the requested +0.2) and
    reports what it executed (ee_shift_applied): the recovery undoes that, and the end-effector ends where
    it started."""
    exp = make_exp(tiny_recipe)
    env = make_chunked_env(exp, seed=0)
    requested = []

    def clipped(delta, safe_lift=0.0):
        requested.append([round(float(x), 6) for x in delta])
        applied = np.minimum(np.asarray(delta, dtype=np.float64), 0.05)
        env.base.ee = env.base.ee + applied
        env.base.ee_offset = env.base.ee_offset + applied
        return applied

    env.base.shift_end_effector = clipped
    r = rollout(exp, exp.make_controller(), env=env)
    assert r["ddp", "mode"].tolist()[2] == 1 and requested[0] == DELTA
    assert shifts(r)[4] == [-0.05, 0.0, 0.0]  # a^rec: minus what the tracking shift executed, not -DELTA
    assert r["next", "ee_shift_applied"][2].tolist() == pytest.approx([0.05, 0.0, 0.0])
    assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


def test_a_recovery_cut_by_the_workspace_is_reported(tiny_recipe):
    """A recovery shift clipped at the workspace's edge has no later shift to undo it: the end-effector stayed
    off without a word (only tracking shifts were read back). Now a warning says by how much."""
    exp = make_exp(tiny_recipe)
    env = make_chunked_env(exp, seed=0)

    def clipped(delta, safe_lift=0.0):
        applied = np.maximum(np.asarray(delta, dtype=np.float64), -0.05)  # the recovery's -x cut at -0.05
        env.base.ee = env.base.ee + applied
        env.base.ee_offset = env.base.ee_offset + applied
        return applied

    env.base.shift_end_effector = clipped
    with pytest.warns(RuntimeWarning, match=r"env 0: the recovery shift \[-0.2.*executed as \[-0.05.*stays "
                                            r"\[-0.15"):
        r = rollout(exp, exp.make_controller(), env=env)
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]
    assert r["next", "privileged", "ee_offset"][-1].tolist() == pytest.approx([0.15, 0.0, 0.0], abs=1e-6)


def test_the_dp3_ablation_tracks_and_recovers_with_the_oracle_detector(tiny_recipe):
    """No world model (the DP3 ablation, ood_tracking with the controller's own tracker): the oracle detector's
    OOD starts tracking at once, though no forecast can ever exist, and the recovery undoes it."""
    tiny_recipe["world_model"]["enabled"] = False
    exp = make_exp(tiny_recipe)
    r = rollout(exp, exp.make_controller())
    assert r["ddp", "mode"].tolist()[2] == 1 and not r["ddp", "imagined"].any()
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]
    assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


def test_nothing_is_tracked_once_every_subtask_has_ended(tiny_recipe):
    """The last subtask's trigger fired at chunk 1, before the displacement is seen (chunk 2): no tracking
    shift, which no recovery could undo any more."""
    exp = make_exp(tiny_recipe, subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 1}}])
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist()[2] == 1 and r["ddp", "subtask"].tolist()[2] == 1
    assert shifts(r) == [[0.0] * 3] * CHUNKS


# --------------------------------------------------------------------------- 5. controller.safe_lift
def test_safe_lift_reaches_the_base_env_and_the_shift_is_exact(tiny_recipe):
    exp = make_exp(tiny_recipe, safe_lift=0.05)
    env = make_chunked_env(exp, seed=0, overrides={"displacement": False})
    assert env.safe_lift == 0.05
    calls = []
    original = env.base.shift_end_effector

    def recording(delta, **kwargs):
        calls.append((np.asarray(delta).tolist(), kwargs))
        return original(delta, **kwargs)

    env.base.shift_end_effector = recording
    td = env.reset()
    before = env.base.ee.copy()
    td["action"] = torch.zeros(8, 4)
    td["ee_shift"] = torch.zeros(3)
    td = env.step(td)["next"]
    assert calls == []  # a zero shift is no call
    assert np.allclose(env.base.ee, before)
    delta = torch.tensor([0.05, -0.03, 0.02])
    td["action"] = torch.zeros(8, 4)
    td["ee_shift"] = delta
    nxt = env.step(td)["next"]
    assert len(calls) == 1 and calls[0][1] == {"safe_lift": 0.05}
    assert np.allclose(calls[0][0], delta.tolist())
    # the synthetic env's shift lands the end-effector exactly delta away (the lift is up-and-back-down)
    assert np.allclose(env.base.ee - before, delta.numpy(), atol=1e-7)
    assert torch.allclose(nxt["agent_pos"][-1, :3] - td["agent_pos"][-1, :3], delta, atol=1e-6)
    assert torch.allclose(nxt["privileged", "ee_offset"], delta)

    # through a controller rollout: the tracking and the recovery shifts both go with safe_lift
    env = make_chunked_env(exp, seed=0)
    calls.clear()
    original = env.base.shift_end_effector
    env.base.shift_end_effector = recording
    r = rollout(exp, exp.make_controller(), env=env)
    assert [(np.round(d, 6).tolist(), kw) for d, kw in calls] == [
        (DELTA, {"safe_lift": 0.05}), ([-d for d in DELTA], {"safe_lift": 0.05})
    ]
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]


# --------------------------------------------------------------------------- 6. the ood_base protocol
def protocol_rollout(exp, name):
    """One episode of a protocol, built the way ddp.evaluate builds it."""
    protocol = get_protocol(name)
    overrides = env_overrides(exp, protocol, exp.recipe.eval.max_steps)
    ctrl = exp.make_controller(detector=protocol.detector, imagine=protocol.imagine, tracker=protocol.tracker)
    return ctrl, rollout(exp, ctrl, **overrides)


def test_ood_base_displaces_but_never_detects_nor_shifts(tiny_recipe):
    exp = make_exp(tiny_recipe)
    exp.parts["env"].config.displacement = False  # the protocol, not the recipe, must turn the displacement on

    ctrl, r = protocol_rollout(exp, "ood_base")
    assert ctrl.tracker is None and ctrl.recovery is None
    displacement = r["next", "privileged", "displacement"][:, 0]
    assert torch.allclose(displacement[1:], torch.tensor(DELTA).expand(CHUNKS - 1, 3))  # the cube was displaced
    assert (r["ddp", "mode"] == 0).all() and not r["ddp", "imagined"].any()
    assert (r["ee_shift"] == 0).all()
    assert torch.allclose(r["next", "privileged", "ee_offset"], torch.zeros(CHUNKS, 3))

    # the same displaced episode under ood_ddp: detected at cycle 2, tracked there, recovered at 4
    ctrl, r = protocol_rollout(exp, "ood_ddp")
    assert torch.allclose(r["next", "privileged", "displacement"][1:, 0], torch.tensor(DELTA).expand(CHUNKS - 1, 3))
    assert r["ddp", "mode"][2] == 1 and shifts(r)[2] == DELTA


# --------------------------------------------------------------------------- review fixes (2026-12-04)
class PerChunkTracker(torch.nn.Module):
    """One object whose offset is scripted per chunk index (``{chunk: [dx, dy, dz]}``, zero elsewhere)."""

    def __init__(self, script):
        super().__init__()
        self.script = script

    def key(self, role):
        return ("ddp", role)

    def forward(self, td):
        chunk = td.get("chunk_index").reshape(-1).tolist()
        td.set(("ddp", "offsets"), torch.tensor([[self.script.get(c, [0.0, 0.0, 0.0])] for c in chunk]))
        return td

    def reset(self):
        pass


def test_a_later_subtasks_target_is_tracked_with_its_offset_when_the_shift_executes(tiny_recipe):
    """OOD begins while a subtask without a target runs; the object moves on before its own subtask begins:
    a^track is the offset seen when that subtask's shift executes, not the one seen when OOD began."""
    exp = make_exp(tiny_recipe, subtasks=[{"target": None, "trigger": {"name": "chunk_index", "chunk": 3}},
                                          {"target": 0, "trigger": {"name": "chunk_index", "chunk": 6}},
                                          {"target": None}])
    ctrl = exp.make_controller()
    ctrl.tracker = PerChunkTracker({2: [0.1, 0.0, 0.0], 3: [0.2, 0.0, 0.0], 4: [0.2, 0.0, 0.0]})
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist()[2] == 1 and shifts(r)[2] == [0.0, 0.0, 0.0]  # no target yet: no shift
    assert shifts(r)[3] == [0.2, 0.0, 0.0]


def test_a_flag_after_the_targets_subtask_ended_is_rechecked(tiny_recipe):
    """The cube's subtask ended (chunk 2) before D_R-I flagged its move (chunk 3): no subtask will track or
    recover it, so the alarm is re-checked as one with nothing displaced is (recheck_until_id: back to reality
    at the first ID verdict) instead of imagining to the episode's end."""
    exp = make_exp(tiny_recipe, recheck_until_id=True,
                   subtasks=[{"target": 0, "trigger": {"name": "chunk_index", "chunk": 2}}, {"target": None}])
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={3, 4})
    r = rollout(exp, ctrl)
    assert r["ddp", "mode"].tolist() == [0, 0, 0, 1, 1, 0, 0, 0]
    assert not any(any(row) for row in shifts(r))


def test_a_non_sticky_detector_keeps_ood_until_the_tracked_target_is_recovered(tiny_recipe):
    """A non-sticky detector that stops reading OOD right after the tracking shift does not end OOD mode
    before the recovery that undoes the shift: the end-effector ends where it started."""
    exp = make_exp(tiny_recipe)
    ctrl = exp.make_controller()
    ctrl.detector = ScriptedStickyDetector(ood_at={2})
    ctrl.detector.sticky = False
    r = rollout(exp, ctrl)
    assert shifts(r)[2] == DELTA and shifts(r)[4] == [-d for d in DELTA]
    assert r["ddp", "mode"].tolist()[2:4] == [1, 1]
    assert torch.allclose(r["next", "privileged", "ee_offset"][-1], ZERO, atol=1e-6)


def test_a_non_finite_applied_shift_never_reaches_the_recovery(tiny_recipe):
    """An env reporting ee_shift_applied NaN: the requested shift counts as executed (with a warning), and
    the recovery shift the controller emits is finite."""
    exp = make_exp(tiny_recipe)
    env = make_chunked_env(exp, seed=0)

    def broken(delta, safe_lift=0.0):
        env.base.ee = env.base.ee + np.asarray(delta)
        env.base.ee_offset = env.base.ee_offset + np.asarray(delta)
        return np.array([np.nan, 0.0, 0.0])

    env.base.shift_end_effector = broken
    with pytest.warns(RuntimeWarning, match="ee_shift_applied"):
        r = rollout(exp, exp.make_controller(), env=env)
    assert torch.isfinite(r["ee_shift"]).all() and shifts(r)[4] == [-d for d in DELTA]


def test_a_subtask_target_beyond_the_trackers_objects_is_one_line(tiny_recipe):
    from ddp.errors import RecipeError

    exp = make_exp(tiny_recipe, subtasks=[{"target": 3, "trigger": {"name": "chunk_index", "chunk": 4}}])
    with pytest.raises(RecipeError, match=r"controller.subtasks\[0\].target: target 3 is not one of the 1 object"):
        rollout(exp, exp.make_controller())


def test_a_recovery_plugin_returning_nan_is_one_line_before_any_shift(tiny_recipe):
    """The built-in recovery negates executed, finite shifts; a plugin's NaN stops in the controller, naming
    the plugin, instead of reaching the env (where a hold setting turned it into another error)."""
    from ddp.safety import NonFiniteError

    exp = make_exp(tiny_recipe)
    ctrl = exp.make_controller()
    recover = ctrl.recovery.recover

    def nan_recover(offsets, displaced, target):
        shift, recovered = recover(offsets, displaced, target)
        return shift * float("nan"), recovered

    ctrl.recovery.recover = nan_recover
    with pytest.raises(NonFiniteError, match=r"environment 0, chunk \d+: recovery '.*' returned a non-finite shift"):
        rollout(exp, ctrl)


def test_plugin_outputs_off_their_contract_are_one_line_and_a_partly_nan_offset_is_no_shift(tiny_recipe):
    """Tracker offsets and recovery results are checked against their contracts before use: a 0-d recovery
    shift broadcast to every axis of the end-effector, a float recovered mask and a tracker's [B, 3] offsets
    failed deep in the controller. An offset with one non-finite component is no displacement at all (zeroing
    that component alone sent the rest as a shift)."""
    from ddp.errors import PluginError

    exp = make_exp(tiny_recipe)

    def with_tracker(edit):
        ctrl = exp.make_controller()
        forward, key = ctrl.tracker.forward, ctrl.tracker.key("offsets")

        def edited(td):
            out = forward(td)
            out.set(key, edit(out.get(key)))
            return out

        ctrl.tracker.forward = edited
        return ctrl

    with pytest.raises(PluginError, match=r"tracker '.*' wrote offsets of torch.float32 \[1, 3\]; .*\[B=1, K, 3\]"):
        rollout(exp, with_tracker(lambda off: off[:, 0]))

    def nan_y(off):
        off = off.clone()
        off[..., 1] = float("nan")
        return off

    r = rollout(exp, with_tracker(nan_y))
    assert not any(any(row) for row in shifts(r))  # never the x component of the move (DELTA) alone

    for bad, match in ((lambda shift, rec: (shift.sum() * 0 - 0.2, rec), r"a shift of torch.float32 \[\]"),
                       (lambda shift, rec: (shift, rec.float()), r"recovered of torch.float32 \[1\]; .*bool \[K=1\]")):
        ctrl = exp.make_controller()
        recover = ctrl.recovery.recover
        ctrl.recovery.recover = lambda o, d, t, bad=bad, recover=recover: bad(*recover(o, d, t))
        with pytest.raises(PluginError, match=match):
            rollout(exp, ctrl)
