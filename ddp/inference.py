"""The DDP controller: closed-loop inference with imagination (paper Algorithm 2).

One call = one control cycle for a batch of environments (``ChunkedEnv``
observations: ``point_cloud`` [B, M, P, 3], ``agent_pos`` [B, M, D],
``chunk_index`` [B, 1], ``privileged`` for oracle parts). Per environment it
keeps the ID/OOD mode, the last imagined latents, the displaced objects and
the current subtask; a new episode (``chunk_index == 0``) resets them.

It writes ``action`` [B, N, A] (the chunk to execute), ``ee_shift`` [B, 3]
(tracking / recovery shift the environment executes before the chunk) and
diagnostics under ``"ddp"``: ``mode`` (0 ID, 1 OOD), ``imagined`` (the
policy acted from imagined latents), ``discrepancy`` (D_R-I, NaN before the
first prediction), ``subtask``. Before the detector runs it writes what
detectors score: ``latent_real`` / ``latent_pred`` [B, M, D] (the real
window and the world model's forecast of it, NaN before the first forecast,
so nothing can flag an episode's first chunk from D_R-I), ``point_dims``
[B] (how many leading latent dims are point-cloud features) and, with
``forecast_samples`` K > 1 (the forecast is then the mean of K world-model
samples), ``latent_pred_std`` [B, M, D], their spread.

Random streams are per episode: each environment's policy noise and world-model noise (two streams) are
seeded from the controller's ``seed`` and the episode's ``episode_seed`` (from the env; without one, the
order in which episodes start), and ``("ddp", "episode_key")`` [B] (int64, written before the tracker and
detector run) carries the episode's key to parts that draw at random (the substitution detector). So an
episode draws the same noise whatever ``--num-envs`` and env row run it, and training seeds draw apart. Where every
cycle needs one (a D_R-I detector, or ``forecast_every_cycle``) it is made right after the chunk is
chosen, and with ``async_forecast`` (the default) in a background thread while the environment
executes the chunk: the robot waits only for encode, detect and the policy, and the results are
those of the inline forecast exactly (on a CPU both run single-threaded: a kernel's sums depend on
how many threads split them). Otherwise forecasts are made lazily, when imagination needs one.

An OOD flag with no displaced object to track (a false alarm, an occlusion,
a sensor fault) is re-checked once, on the next cycle: D_R-I at or below tau
returns to reality, above it the controller imagines on (to the episode's end,
unless a recovery re-checks again; ``recheck_until_id`` re-checks every cycle).

A displaced object is tracked (``a^track = Delta p``) when the subtask that targets it is the current one
in OOD mode: at the OOD onset, when the tracker first sees it move, or when its subtask begins; its
recovery (``a^rec = -Delta p``) moves the end-effector only if it was tracked, by what the tracking shift
executed (the env's ``ee_shift_applied``: a shift clipped at the workspace's edge is undone as clipped), and
reality does not resume while a tracked object waits for its recovery, so the shifts of an episode sum to zero
once every tracked target's subtask has ended (a recipe's last subtask, without a trigger, ends with the
episode: its tracking shift stays). A recovery clipped at the workspace's edge has nothing left to undo it: a
warning says by how much the end-effector stays off.

Nothing non-finite leaves it: observations are validated at the boundary
(``ddp.safety.check_observation``); an environment whose observation or latents
are not finite counts as OOD and acts from imagination when a forecast exists (a forecast
that came out non-finite counts as OOD too, D_R-I inf, and is not acted on);
otherwise, or if the sampled actions are not finite, ``on_nonfinite`` decides:
``"raise"`` (a one-line :class:`~ddp.safety.NonFiniteError`) or ``"hold"`` (the
env's hold action: zero motion, gripper command unchanged; ``("ddp", "held")``).
A chunk held for non-finite actions is forecast like any other (W_phi of its
latents and the hold chunk), so the next cycle has a D_R-I and can imagine.
"""

from __future__ import annotations

import inspect
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase

from ddp.contracts import check as check_contract
from ddp.detectors.scores import ScoreSpec, residual_score
from ddp.errors import PluginError, RecipeError
from ddp.keys import KeyedModule
from ddp.rng import ACTIONS, FORECASTS, generator, mix
from ddp.safety import DELTAS, HoldSpec, NonFiniteError, ObservationSpec, check_observation, first_nonfinite

MIN_OFFSET = 1e-6  # metres: smaller tracked offsets mean "did not move"
#: metres: after a resume_after_recovery, a tracked offset this far from the accepted one is a new displacement
NEW_DISPLACEMENT = 0.02


@dataclass
class Subtask:
    target: int | None  # index of the target object C_j in the privileged object order
    trigger: object | None  # completion trigger T_end(S_j); None = ends with the episode


@dataclass
class EnvState:
    """What Algorithm 2 keeps per environment between cycles."""

    ood: bool = False  # OOD_Mode
    recheck_after: int | None = None  # re-evaluate D_R-I on the first observation after this chunk
    predicted: torch.Tensor | None = None  # W_phi's forecast of the next N latents
    spread: torch.Tensor | None = None  # std over the K forecast samples (forecast_samples > 1)
    pending: tuple | None = None  # (O_curr, a_t) of the last cycle, forecast lazily when needed

    @property
    def has_forecast(self) -> bool:
        return self.predicted is not None or self.pending is not None
    offsets: torch.Tensor | None = None  # Delta p_C per object, from the tracker
    displaced: torch.Tensor | None = None  # C_disp as a mask over objects
    recovered: torch.Tensor | None = None  # objects already brought back
    tracked: torch.Tensor | None = None  # objects whose a^track the end-effector executed (a^rec undoes it)
    followed: torch.Tensor | None = None  # [K, 3] the a^track each object's shift executed (as the env applied it)
    last_track: int | None = None  # the object tracked in the last cycle, whose applied shift is read back
    last_shift: torch.Tensor | None = None  # the shift requested in that cycle
    deferred_track: int | None = None  # a target whose a^track a held chunk took back: tracked on a cycle that acts
    subtask: int = 0
    subtask_start: int = 0
    trigger_state: dict = field(default_factory=dict)  # the current subtask's trigger's memory (fired(state=))
    # resume_after_recovery: the tracked offsets when the controller returned to reality with displaced
    # objects no subtask targets left where they are; only a displacement beyond them re-enters OOD
    accepted: torch.Tensor | None = None
    last_action: torch.Tensor | None = None  # the last finite action emitted (what "hold" repeats)
    key: int | None = None  # the episode's random key (ddp.rng.mix of the controller's seed and the episode's)
    rng: torch.Generator | None = None  # the policy's sampling noise, this episode's stream
    forecast_rng: torch.Generator | None = None  # the world model's forecast noise, this episode's stream


def _takes_state(trigger) -> bool:
    """Whether ``trigger.fired`` takes the optional ``state`` keyword (see :class:`ddp.contracts.Trigger`)."""
    try:
        params = inspect.signature(trigger.fired).parameters
    except (TypeError, ValueError):
        return False
    return "state" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


class DDPController(KeyedModule):
    """Detect (D_R-I) -> track -> imagine -> recover, around a trained DreamDiffusionPolicy."""

    default_in_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos", "chunk_index": "chunk_index",
                       "ee_shift_applied": "ee_shift_applied", "episode_seed": "episode_seed"}
    default_out_keys = {
        "action": "action",
        "ee_shift": "ee_shift",
        "mode": ("ddp", "mode"),
        "imagined": ("ddp", "imagined"),
        "discrepancy": ("ddp", "discrepancy"),
        "subtask": ("ddp", "subtask"),
        "held": ("ddp", "held"),
        "latent_real": ("ddp", "latent_real"),
        "latent_pred": ("ddp", "latent_pred"),
        "point_dims": ("ddp", "point_dims"),
        "episode_key": ("ddp", "episode_key"),
        "latent_pred_std": ("ddp", "latent_pred_std"),
    }

    def __init__(
        self,
        model,
        *,
        detector,
        tracker=None,
        recovery=None,
        subtasks: list[Subtask] | None = None,
        imagine: bool = True,
        track: bool = True,
        forecast_every_cycle: bool = False,
        forecast_samples: int = 1,
        async_forecast: bool = True,
        seed: int = 0,
        on_nonfinite: str = "raise",
        hold: HoldSpec | None = None,
        num_points: int | None = None,
        resume_after_recovery: bool = False,
        recheck_until_id: bool = False,
    ):
        super().__init__()
        for kind, part in (("detector", detector), ("tracker", tracker), ("recovery", recovery)):
            if part is not None:  # parts built in code, not from a recipe, are held to their contracts here
                check_contract(kind, part, name=type(part).__name__, module=type(part).__module__)
        for sub in subtasks or []:
            if sub.trigger is not None:
                check_contract("trigger", sub.trigger, name=type(sub.trigger).__name__)
        if forecast_samples < 1:
            raise ValueError(f"forecast_samples must be >= 1; got {forecast_samples}")
        if on_nonfinite not in ("raise", "hold"):
            raise ValueError(f"on_nonfinite must be 'raise' or 'hold'; got {on_nonfinite!r}")
        if on_nonfinite == "hold" and hold is None:  # e.g. a Franka gripper held at 0 would read as "open"
            raise ValueError("on_nonfinite='hold' needs hold=, how the env holds still (its action_hold, e.g. "
                             "ddp.safety.DELTAS for an env whose every action dim is a delta)")
        if hold is not None:
            hold.absolute_dims(model.action_dim)  # a spec for another action space: refused now, not at a fault
        bad = first_nonfinite([*model.named_parameters(), *model.named_buffers()])
        if bad is not None:
            raise NonFiniteError(f"the model's '{bad}' holds NaN or inf: it cannot drive a robot")
        if detector.needs_discrepancy and not model.has_world_model:
            raise ValueError("the discrepancy detector needs a world model (world_model.enabled is false)")
        if imagine and not model.has_world_model:
            imagine = False  # the DP3 ablation: tracking without imagination
        self.model = model
        self.detector = detector
        self.tracker = tracker
        self.recovery = recovery
        self.subtasks = subtasks or [Subtask(target=0, trigger=None)]
        self.imagine = imagine
        self.track = track
        self.resume_after_recovery = resume_after_recovery
        self.recheck_until_id = recheck_until_id
        self._forecast_every_cycle = forecast_every_cycle
        self._async_forecast = async_forecast
        self.forecast_samples = forecast_samples
        self._pool: ThreadPoolExecutor | None = None  # one background thread for the forecasts
        self._job: tuple[list[int], Future] | None = None  # the forecast being made while the chunk executes
        self.seed = seed
        self.on_nonfinite = on_nonfinite
        self.hold = DELTAS if hold is None else hold  # used by "hold" only, which is given one
        self.obs_spec = ObservationSpec(model.obs_steps, model.agent_pos_dim, model.point_dim, num_points)
        self.reset()

    @property
    def forecast_every_cycle(self) -> bool:
        """Forecasts are made right after each chunk is chosen (a D_R-I detector needs one every cycle);
        otherwise lazily, when imagination needs one. Read each cycle: a detector swapped in later counts."""
        return self._forecast_every_cycle or self.detector.needs_discrepancy

    @property
    def async_forecast(self) -> bool:
        """Those forecasts are made in the background thread while the chunk executes."""
        return self._async_forecast and self.forecast_every_cycle and self.model.has_world_model

    def __getstate__(self):
        """Copies and pickles (e.g. a collector moving the policy) leave the forecast thread behind; the
        forecast it was making is stored first, so a copy's next cycle has it (a D_R-I to score)."""
        self._collect()
        state = super().__getstate__() if hasattr(super(), "__getstate__") else self.__dict__
        return {**state, "_pool": None, "_job": None}

    @property
    def device(self) -> torch.device:
        """Where the model's weights are: observations go there, actions come back to the env's device."""
        return next(self.model.parameters()).device

    def _drop_forecast(self, when: str) -> None:
        """Wait for the background forecast, if one runs, and drop it; its error becomes a warning (no
        cycle will collect it any more)."""
        job, self._job = getattr(self, "_job", None), None
        error = job[1].exception() if job is not None else None  # waits for it
        if error is not None:
            warnings.warn(f"controller: the last background world-model forecast failed and was dropped at "
                          f"{when}: {error!r}", RuntimeWarning, stacklevel=3)

    def reset(self) -> None:
        self._drop_forecast("reset")  # a forecast for the previous episodes
        self.states: list[EnvState] = []
        self._episodes_started = 0  # numbers the episodes of envs that do not tell their episode_seed
        for part in (self.detector, self.tracker, self.recovery):  # each contract has reset()
            if part is not None:
                part.reset()

    # ------------------------------------------------------------------ helpers
    def _seed_episodes(self, td: TensorDictBase, dev: torch.device) -> None:
        """Give each episode that starts its random streams, keyed by the controller's seed and the episode's
        ``episode_seed`` (the env's; without it, the count of episodes started), on the model's device."""
        seeds = td.get(self.key("episode_seed"), None)
        for b, s in enumerate(self.states):
            if s.key is None:
                if seeds is not None:
                    s.key = mix(self.seed, int(seeds[b].reshape(-1)[0]))
                else:
                    s.key = mix(self.seed, -1, self._episodes_started)
                    self._episodes_started += 1
            if s.rng is None or s.rng.device != dev:  # new, or the model moved: the episode's streams afresh
                s.rng, s.forecast_rng = generator(mix(s.key, ACTIONS), dev), generator(mix(s.key, FORECASTS), dev)

    def _trigger(self, s: EnvState):
        if self.recovery is not None and self.recovery.trigger_chunk is not None:
            return ("chunk", self.recovery.trigger_chunk)
        return self.subtasks[s.subtask].trigger if s.subtask < len(self.subtasks) else None

    def _targets_recovered(self, s: EnvState) -> bool:
        """Something was recovered and every displaced object that the current or a later subtask targets has
        been (displaced objects no such subtask targets, e.g. coffee-pull's machine, are scenery the policy may
        see where they now are)."""
        if s.displaced is None or s.recovered is None:
            return False
        return bool(s.recovered.any()) and not self._targets_to_recover(s)

    def _targets_to_recover(self, s: EnvState) -> list[int]:
        """The displaced objects that the current or a later subtask targets and that are not recovered yet
        (an ended subtask's recovery is past: its target will not be brought back)."""
        targets = {sub.target for sub in self.subtasks[s.subtask:] if sub.target is not None}
        return [k for k in targets if k < len(s.displaced) and bool(s.displaced[k]) and not bool(s.recovered[k])]

    def _left_to_recover(self, s: EnvState) -> bool:
        """A displaced object that the current or a later subtask targets is not recovered yet (its recovery is
        to come); other displaced objects are scenery, or an ended subtask's target, that no recovery will
        bring back."""
        if s.displaced is None or s.recovered is None:
            return False
        return bool(self._targets_to_recover(s))

    @staticmethod
    def _awaits_recovery(s: EnvState) -> bool:
        """The end-effector executed a^track for an object whose a^rec has not come yet (its subtask runs), or a
        held chunk took back the a^track of its subtask's target (it comes on the next cycle that acts)."""
        if s.deferred_track is not None:
            return True
        return s.tracked is not None and bool((s.tracked & ~s.recovered).any())

    @staticmethod
    def _accepted_scene(s: EnvState, offsets: torch.Tensor | None, b: int) -> bool:
        """The tracker sees nothing displaced beyond what was accepted when the controller resumed reality
        after a recovery (D_R-I stays high while the scene stays changed; only a new displacement counts).
        An object whose offset reads zero (hidden, carried, or back at its ID place) is no new displacement."""
        if s.accepted is None or offsets is None:
            return False
        seen = offsets[b].norm(dim=-1) > MIN_OFFSET
        return bool(((offsets[b] - s.accepted).norm(dim=-1)[seen] <= NEW_DISPLACEMENT).all())

    @staticmethod
    def _scene_to_accept(s: EnvState, offsets: torch.Tensor | None, measured, b: int) -> torch.Tensor | None:
        """The offsets accepted when reality resumes: what the tracker sees now, and for an object it cannot
        see (``measured`` False) the offset it was last tracked at, so its reappearance there is no new event."""
        if offsets is None:
            return None
        known = s.offsets if s.offsets is not None else torch.zeros_like(offsets[b])
        return torch.where(measured[b][:, None], offsets[b], known).clone()

    def _measured(self, td, offsets: torch.Tensor | None, finite: torch.Tensor | None) -> torch.Tensor | None:
        """[B, K] which objects the tracker measured this cycle: its optional ``"visible"`` output (a depth
        tracker sees an object back at its place, offset 0, as well as a moved one) less the objects it calls
        ``"carried"`` (their offset reads 0 in the hand) and those whose offset was not finite (``finite``,
        before cleaning); without the role, a non-zero offset (the oracle's zero reads "not displaced", and an
        unmeasured offset reads zero)."""
        if offsets is None:
            return None
        shown = offsets.norm(dim=-1) > MIN_OFFSET
        visible = self._tracker_mask(td, "visible", shown.shape)
        if visible is None:
            return shown
        carried = self._tracker_mask(td, "carried", shown.shape)
        return visible & finite & (~carried if carried is not None else True)

    def _tracker_mask(self, td, role: str, shape) -> torch.Tensor | None:
        """The tracker's optional [B, K] bool output ``role``; None if it has no such role or wrote none."""
        try:
            key = self.tracker.key(role)
        except KeyError:  # a tracker without the role
            return None
        mask = td.get(key, None)
        return mask.cpu().bool() if isinstance(mask, torch.Tensor) and mask.shape == shape else None

    def _track(self, s: EnvState, b: int, ee_shift: torch.Tensor, offsets: torch.Tensor) -> None:
        """a^track_j = Delta p_Cj for the current subtask's target, if it is displaced and not yet tracked
        or recovered (``offsets``: this environment's [K, 3]). Once every subtask has ended (the last one's
        trigger fired) there is no current target: a shift then would have no recovery left to undo it."""
        if s.subtask >= len(self.subtasks):
            return
        target = self.subtasks[s.subtask].target
        if (not self.track or target is None or s.displaced is None or not bool(s.displaced[target])
                or bool(s.recovered[target]) or bool(s.tracked[target])):
            return
        ee_shift[b] += offsets[target]
        s.tracked[target] = True
        s.followed[target] = offsets[target]
        s.last_track = target
        s.deferred_track = None

    def _defer_track(self, s: EnvState, b: int, ee_shift: torch.Tensor) -> None:
        """Take back the a^track :meth:`_track` added this cycle (at most one: an object is tracked once), for
        a held chunk: the arm does not move on a cycle whose observation or actions are not trusted."""
        if s.last_track is None:
            return
        target, s.last_track = s.last_track, None
        ee_shift[b] -= s.followed[target]
        s.tracked[target] = False
        s.followed[target] = torch.zeros_like(s.followed[target])
        s.deferred_track = target  # OOD until it is tracked (or its subtask ends: nothing executed to undo)

    def _read_back_shifts(self, td) -> None:
        """The env's ``ee_shift_applied`` (ChunkedEnv: the shift it executed, clipped to its workspace) for the
        last cycle's request: what clipping cut from it is taken from that cycle's a^track, so the object's
        a^rec undoes the shift that happened. Without the key the requested shift counts as executed."""
        applied = td.get(self.key("ee_shift_applied"), None)
        for b, s in enumerate(self.states):
            if applied is not None and s.last_shift is not None:
                done = applied[b].float().cpu().reshape(-1)
                if not (done.shape == (3,) and bool(torch.isfinite(done).all())):
                    # an env reporting NaN / inf: its shift must not reach a recovery (nor a robot)
                    warnings.warn(f"controller: env {b} reported ee_shift_applied {done.tolist()}; the requested "
                                  f"shift counts as executed", RuntimeWarning, stacklevel=3)
                elif s.last_track is not None:
                    s.followed[s.last_track] = s.followed[s.last_track] + done - s.last_shift
                elif not torch.allclose(done, s.last_shift, atol=1e-6):  # a recovery alone: nothing left to undo it
                    warnings.warn(f"controller: env {b}: the recovery shift {s.last_shift.tolist()} executed as "
                                  f"{done.tolist()} (clipped at the workspace's edge); the end-effector stays "
                                  f"{(s.last_shift - done).tolist()} off", RuntimeWarning, stacklevel=3)
            s.last_track = s.last_shift = None

    def _recover(self, followed: torch.Tensor, displaced: torch.Tensor, target):
        """The recovery plugin's (shift [3], recovered [K] bool), checked against its contract before use: a 0-d
        shift broadcast to every axis of the end-effector, a float mask failed deep in the controller."""
        shift, recovered = self.recovery.recover(followed, displaced, target)
        name = type(self.recovery).__name__
        shift = torch.as_tensor(shift)
        if not shift.is_floating_point() or tuple(shift.shape) != (3,):
            raise PluginError(f"controller: recovery '{name}' returned a shift of {shift.dtype} {list(shift.shape)}; "
                              f"the recovery contract is a float [3] end-effector shift")
        recovered = torch.as_tensor(recovered)
        if recovered.dtype != torch.bool or tuple(recovered.shape) != tuple(displaced.shape):
            raise PluginError(f"controller: recovery '{name}' returned recovered of {recovered.dtype} "
                              f"{list(recovered.shape)}; the recovery contract is a bool [K={displaced.shape[0]}] mask")
        return shift.to(torch.float32), recovered

    def _subtask_ended(self, s: EnvState, obs, chunk: int) -> bool:
        trig = self._trigger(s)
        if trig is None:
            return False
        if isinstance(trig, tuple):  # a recovery at a fixed chunk (oracle snap-back): once per episode
            return chunk >= trig[1] and s.subtask_start < trig[1] and s.subtask < len(self.subtasks)
        if _takes_state(trig):  # a trigger with memory: its own per environment, empty when a subtask starts
            return trig.fired(obs, chunk, chunk - s.subtask_start, state=s.trigger_state)
        return trig.fired(obs, chunk, chunk - s.subtask_start)

    def _imagine(self, history: torch.Tensor, actions: torch.Tensor,
                 generators: list[torch.Generator]) -> tuple[torch.Tensor, torch.Tensor | None]:
        """O_pred = W_phi(O_curr, a_t), batched: the forecast and, with K > 1 samples, their spread (each
        environment's noise from its episode's forecast stream, ``generators``).

        Runs in the calling thread or the background one (grad mode is per thread, hence no_grad here).
        """
        with torch.no_grad():
            k = self.forecast_samples
            if k == 1:
                return self.model.imagine(history, actions, generator=generators), None
            # K samples in one batched call: their mean is the forecast, their std its uncertainty
            samples = self.model.imagine(history.repeat(k, 1, 1), actions.repeat(k, 1, 1), generator=generators * k)
            samples = samples.reshape(k, history.shape[0], *samples.shape[1:])
            return samples.mean(0), samples.std(0)

    def _imagine_one_thread(self, history: torch.Tensor, actions: torch.Tensor, generators: list[torch.Generator]):
        """The forecast with torch's CPU ops single-threaded while it runs, on the background thread or inline.

        ``torch.set_num_threads`` sets the calling thread's OpenMP count (and the global default a thread takes
        at its first torch call: a thread whose first torch op fell inside a forecast would keep 1; none in
        ddp starts then). A second multi-threaded OpenMP team in the process makes libgomp throttle its
        spinning for every team: measured on 2 cores, the main thread's policy then ran 1.5-2.5x slower for
        the rest of the process. With one thread here no second team exists; the count is restored when the
        forecast ends (while it runs, the main thread executes the chunk). The
        inline forecast runs single-threaded too: a CPU kernel's sums depend on how many threads split
        them, and the two paths must give the same forecast, bit for bit.
        """
        threads = torch.get_num_threads()
        if self.device.type == "cpu" and threads > 1:
            torch.set_num_threads(1)
        try:
            return self._imagine(history, actions, generators)
        finally:
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)

    def _store(self, envs: list[int], predicted: torch.Tensor, spread: torch.Tensor | None) -> None:
        for i, b in enumerate(envs):
            self.states[b].predicted, self.states[b].pending = predicted[i], None
            self.states[b].spread = None if spread is None else spread[i]

    def _pending(self, envs: list[int]) -> tuple[list[int], torch.Tensor, torch.Tensor, list] | None:
        todo = [b for b in envs if self.states[b].pending is not None]
        if not todo or not self.model.has_world_model:
            return None
        return (todo, torch.stack([self.states[b].pending[0] for b in todo]),
                torch.stack([self.states[b].pending[1] for b in todo]), [self.states[b].forecast_rng for b in todo])

    def _forecast(self, envs: list[int], one_thread: bool = False) -> None:
        """O_pred = W_phi(O_curr, a_t) for the listed environments, one batched world-model call.

        Lazy forecasts are made here, when D_R-I or imagination needs them, and the inline next-cycle
        forecast (``one_thread``, as its background twin runs); a background forecast (``async_forecast``)
        is collected by :meth:`forward` first.
        """
        pending = self._pending(envs)
        if pending is not None:
            imagine = self._imagine_one_thread if one_thread else self._imagine
            self._store(pending[0], *imagine(*pending[1:]))

    def wait_forecast(self) -> None:
        """Block until the background forecast (``async_forecast``), if one is running, is done."""
        if self._job is not None:
            self._job[1].exception()  # waits; an error surfaces when the result is collected

    def _collect(self) -> None:
        """Store the forecast made in the background while the last chunk executed (it raises its error)."""
        if self._job is not None:
            envs, job = self._job
            self._job = None
            self._store(envs, *job.result())

    def _forecast_next(self) -> None:
        """The next cycle's forecast, made now: inline, or in the background thread (``async_forecast``)."""
        envs = list(range(len(self.states)))
        if not self.async_forecast:
            self._forecast(envs, one_thread=True)  # single-threaded like the background forecast: the same bits
            return
        pending = self._pending(envs)
        if pending is None:
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ddp-forecast")
        self._job = (pending[0], self._pool.submit(self._imagine_one_thread, *pending[1:]))

    def close(self) -> None:
        """Wait for a background forecast and stop its thread (also done when the controller is collected).
        A forecast that failed is reported as a warning (no cycle will collect its error any more)."""
        self._drop_forecast("close")
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __del__(self):
        pool = self.__dict__.get("_pool")
        if pool is not None:
            pool.shutdown(wait=False)

    # ------------------------------------------------------------------ safety
    def _usable(self, latents: torch.Tensor | None) -> bool:
        return latents is not None and bool(torch.isfinite(latents).all())

    def _hold_or_raise(self, b: int, chunk: int, why: str) -> torch.Tensor:
        """The hold chunk for environment ``b`` (``on_nonfinite: hold``), or a NonFiniteError."""
        where = f"controller: environment {b}, chunk {chunk}: {why}"
        if self.on_nonfinite == "raise":
            raise NonFiniteError(f"{where}; refusing to emit an action (controller.on_nonfinite: raise)")
        held = self.hold.action(self.states[b].last_action, self.model.action_dim, self.model.action_steps)
        if held is None:
            raise NonFiniteError(f"{where}; cannot hold before the episode's first finite action (the env's "
                                 "absolute action dimensions have no reset value)")
        return held

    # ------------------------------------------------------------------ one cycle
    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        unbatched = td.batch_dims == 0
        if unbatched:
            td = td.unsqueeze(0)
        dev = self.device
        # Observations checked at the boundary: one line for a wrong key, shape or dtype;
        # ``finite[b]`` False for an environment whose point cloud or agent_pos holds NaN / inf.
        point_cloud, agent_pos, chunk_index, finite = check_observation(
            td, self.obs_spec, self._keys, dtype=next(self.model.parameters()).dtype
        )
        B, M = point_cloud.shape[0], self.model.obs_steps
        env_device = td.get(self.key("point_cloud")).device
        self._collect()  # the forecast made while the last chunk executed (async_forecast)
        if len(self.states) != B:
            self.states = [EnvState() for _ in range(B)]
        for b in range(B):
            if chunk_index[b] == 0:
                self.states[b] = EnvState()
        self._seed_episodes(td, dev)
        td.set(self.key("episode_key"), torch.tensor([s.key for s in self.states], dtype=torch.int64))

        # O_real^t = E_psi(X_real^t), on the model's device (the env's tensors may live elsewhere)
        real = self.model.encode(point_cloud.to(dev), agent_pos.to(dev))
        # a non-finite observation, or latents that came out non-finite, are not reality: OOD
        finite = finite & torch.isfinite(real).flatten(1).all(1).cpu()
        ee_shift = torch.zeros(B, 3)
        # what detectors score: the real window and its forecast (NaN before the first forecast)
        nan = torch.full_like(real[0], float("nan"))
        predicted = torch.stack([s.predicted[-M:].to(real) if s.predicted is not None else nan for s in self.states])
        # a forecast that came out non-finite (the world model's fault) is no "forecast yet": a detector reading
        # its NaN D_R-I as one would never alarm again; it is OOD, acted on from real latents (nothing to imagine)
        broken = torch.tensor([s.predicted is not None and not bool(torch.isfinite(s.predicted).all())
                               for s in self.states])
        for b in torch.nonzero(broken).flatten().tolist():
            warnings.warn(f"controller: environment {b}: the world model's forecast is not finite; this cycle counts "
                          f"as OOD and acts from the real latents", RuntimeWarning, stacklevel=2)
        # D_R-I = ||O_real - O_pred||^2 over the M latest frames and the latent dims (the paper's statistic);
        # a non-finite observation or forecast reads inf
        discrepancy = residual_score(real, predicted, ScoreSpec()).float().cpu()
        td.set(self.key("discrepancy"), torch.where(finite & ~broken, discrepancy, torch.tensor(float("inf"))))
        td.set(self.key("latent_real"), real.float().to(env_device))
        td.set(self.key("latent_pred"), predicted.float().to(env_device))
        td.set(self.key("point_dims"), torch.full((B,), self.model.point_dims, dtype=torch.int64))
        if self.forecast_samples > 1:  # the spread exists exactly where the forecast does
            td.set(self.key("latent_pred_std"), torch.stack([
                s.spread[-M:].to(real) if s.spread is not None else nan for s in self.states
            ]).float().to(env_device))

        # Delta p_C per tracked object [B, K, 3]: the tracker's output sizes the object masks (K = 0 without one)
        offsets = self.tracker(td).get(self.tracker.key("offsets")) if self.tracker is not None else None
        if offsets is not None:
            if not (isinstance(offsets, torch.Tensor) and offsets.is_floating_point() and offsets.dim() == 3
                    and offsets.shape[0] == B and offsets.shape[-1] == 3):  # a plugin's fault: before any use
                what = (f"{offsets.dtype} {list(offsets.shape)}" if isinstance(offsets, torch.Tensor)
                        else type(offsets).__name__)
                raise PluginError(f"controller: tracker '{type(self.tracker).__name__}' wrote offsets of {what}; "
                                  f"the tracker contract is a float [B={B}, K, 3] tensor (one row per object)")
            # an offset the tracker could not measure (any component non-finite) is no displacement, whole:
            # zeroing NaN components alone made [nan, 0.15, 0] a 15 cm shift along y
            offsets = offsets.cpu().float()
            finite_offsets = torch.isfinite(offsets).all(-1)
            offsets = torch.where(finite_offsets[..., None], offsets, torch.zeros(()))
        measured = self._measured(td, offsets, finite_offsets if offsets is not None else None)
        num_objects = offsets.shape[-2] if offsets is not None else 0
        if offsets is not None:
            for j, sub in enumerate(self.subtasks):
                if sub.target is not None and not 0 <= sub.target < num_objects:
                    raise RecipeError(f"target {sub.target} is not one of the {num_objects} object(s) the tracker "
                                      f"follows (0..{num_objects - 1})", key=f"controller.subtasks[{j}].target")
        for s in self.states:
            if s.recovered is None:
                s.recovered = torch.zeros(num_objects, dtype=torch.bool)
                s.tracked = torch.zeros(num_objects, dtype=torch.bool)
                s.followed = torch.zeros(num_objects, 3)
        self._read_back_shifts(td)
        if offsets is not None:
            # objects recovered before this cycle (a recovery below is only observable from the next one)
            td.set(("ddp", "recovered"), torch.stack([s.recovered.clone() for s in self.states]))

        # 3. Target-specific recovery at the end of a subtask (checked on the latest observation)
        for b, s in enumerate(self.states):
            if not self._subtask_ended(s, td[b], chunk_index[b]):
                continue
            target = self.subtasks[min(s.subtask, len(self.subtasks) - 1)].target
            if s.ood and s.displaced is not None and self.recovery is not None:
                followed = torch.where(s.tracked[:, None], s.followed, s.offsets)  # tracked: what was executed
                shift, recovered = self._recover(followed, s.displaced & ~s.recovered, target)
                if not bool(torch.isfinite(shift).all()):  # a plugin's fault
                    raise NonFiniteError(f"controller: environment {b}, chunk {int(chunk_index[b])}: recovery "
                                         f"'{type(self.recovery).__name__}' returned a non-finite shift "
                                         f"{shift.tolist()}; no shift is sent")
                if target is not None and bool(s.tracked[target]):  # a^rec_j = -Delta p_Cj undoes a^track_j
                    ee_shift[b] += shift
                s.recovered |= recovered
                if bool(recovered.any()):
                    s.recheck_after = chunk_index[b]  # re-evaluate D_R-I once the shift is observed
            s.subtask, s.subtask_start, s.trigger_state = s.subtask + 1, chunk_index[b], {}
            s.deferred_track = None  # its target's shift never executed: nothing is left to track or undo

        # 1. OOD detection & tracking
        ood_now = self.detector(td).get(self.detector.key("ood")).reshape(B).tolist()
        ood_now = [bool(o) or not bool(finite[b]) or bool(broken[b]) for b, o in enumerate(ood_now)]  # non-finite: OOD
        for b, s in enumerate(self.states):
            # a non-sticky detector (oracle, substitution) enters OOD once there is a forecast to imagine from,
            # or at once for a controller that does not imagine (the DP3 ablation: tracking on real latents)
            if (not s.ood and ood_now[b] and (self.detector.sticky or s.has_forecast or not self.imagine
                                               or not finite[b])
                    and not (finite[b] and self._accepted_scene(s, offsets, b))):
                s.ood = True  # OOD_Mode <- True
                if not finite[b]:  # a sensor fault, not a displacement: re-check D_R-I once inputs are finite
                    s.recheck_after = chunk_index[b]
                if offsets is not None:
                    s.offsets = offsets[b]
                    s.displaced = (offsets[b].norm(dim=-1) > MIN_OFFSET) & ~s.recovered
                    self._track(s, b, ee_shift, offsets[b])  # a^track_j = Delta p_Cj
                if s.displaced is None or not self._left_to_recover(s):
                    # nothing displaced that a subtask still to come tracks or recovers (scenery, or the target
                    # of a subtask that already ended): re-check D_R-I next cycle
                    s.recheck_after = chunk_index[b]
            elif s.ood and not self.detector.sticky:
                # re-decided every cycle (substitution, simulator oracle), but not while a tracking shift waits
                # for the recovery that undoes it
                s.ood = bool(ood_now[b]) or self._awaits_recovery(s)
            elif s.ood and s.recheck_after is not None and chunk_index[b] > s.recheck_after and finite[b]:
                s.recheck_after = None
                if self._awaits_recovery(s):
                    pass  # a tracking shift its recovery has not undone yet: OOD until then (it re-checks again)
                elif not ood_now[b]:
                    s.ood = False  # D_R-I <= tau: return to reality
                elif self.resume_after_recovery and self._targets_recovered(s):
                    s.ood = False  # every displaced target is back: reality, with the rest of the scene as it is
                    s.accepted = self._scene_to_accept(s, offsets, measured, b)
                elif self.recheck_until_id and not self._left_to_recover(s):
                    s.recheck_after = chunk_index[b]  # nothing left to track or recover: re-check next cycle too

        # Keep tracking in OOD mode: an object the tracker could not see when OOD began (zero
        # offset, e.g. hidden behind the arm) joins C_disp once it is seen displaced; the current
        # subtask's target is tracked if it is displaced and was not yet (seen now, or displaced all
        # along while an earlier subtask ran).
        for b, s in enumerate(self.states):
            if not (s.ood and offsets is not None and s.displaced is not None):
                continue
            visible = offsets[b].norm(dim=-1) > MIN_OFFSET
            seen = visible & ~s.displaced & ~s.recovered
            if bool(seen.any()):
                s.offsets = torch.where(seen[:, None], offsets[b], s.offsets)
                s.displaced |= seen
            # a^track = p_Cj - p_Cj^exp when it executes: the offset measured now (zero for an object seen back
            # at its place), or the last one known for an object it cannot measure now (hidden, carried)
            self._track(s, b, ee_shift, torch.where(measured[b][:, None], offsets[b], s.offsets))

        # O_curr: real latents in ID, imagined ones in OOD (Enter Imagination)
        imagined = [self.imagine and s.ood and s.has_forecast for s in self.states]
        self._forecast([b for b in range(B) if imagined[b]])
        imagined = [imagined[b] and self._usable(self.states[b].predicted) for b in range(B)]
        current = torch.stack(
            [self.states[b].predicted[-M:] if imagined[b] else torch.nan_to_num(real[b]) for b in range(B)]
        )

        # 2. Action execution & recursive imagination
        chunk = self.model.sample_actions(current, generator=[s.rng for s in self.states])
        actions = self.model.executed_actions(chunk).cpu()
        # A robot never receives a non-finite action: an environment that can neither trust its
        # observation nor imagine, or whose actions came out non-finite, holds still (or we raise).
        held = [False] * B
        grounded = [bool(finite[b]) or imagined[b] for b in range(B)]  # O_curr is real or imagined latents
        for b in range(B):
            if not grounded[b]:
                why = "the observation (or its latents) is not finite and there is no imagined forecast to act from"
            elif not bool(torch.isfinite(actions[b]).all()):
                why = "the policy produced a non-finite action"
            else:
                self.states[b].last_action = actions[b, -1].clone()
                continue
            # the chunk holds still, and so does a tracking shift decided this cycle: it waits for a chunk that
            # acts (tracked again then, from that cycle's offsets); a recovery due at the subtask's end runs
            actions[b], held[b] = self._hold_or_raise(b, chunk_index[b], why), True
            self._defer_track(self.states[b], b, ee_shift)
        if self.model.has_world_model:
            # O_pred for the next cycle is W_phi(O_curr, a_t): in ID the forecast D_R-I compares
            # against, in OOD the autoregressive imagination the policy acts from (made lazily). A held
            # chunk is what executes: forecast from it, unless O_curr itself is no latent (a non-finite
            # observation with nothing imagined).
            for b, s in enumerate(self.states):
                s.pending = (current[b], actions[b].to(dev)) if grounded[b] else None
                s.predicted, s.spread = None, None
            if self.forecast_every_cycle:  # now, or in the background while the chunk executes
                self._forecast_next()

        for b, s in enumerate(self.states):  # read back next cycle (ee_shift_applied)
            s.last_shift = ee_shift[b].clone() if s.last_track is not None or bool(ee_shift[b].any()) else None
        td.set(self.key("action"), actions.to(env_device))
        td.set(self.key("ee_shift"), ee_shift)
        td.set(self.key("held"), torch.tensor(held))
        td.set(self.key("mode"), torch.tensor([int(s.ood) for s in self.states]))
        td.set(self.key("imagined"), torch.tensor(imagined))
        td.set(self.key("subtask"), torch.tensor([s.subtask for s in self.states]))
        return td.squeeze(0) if unbatched else td
