"""One declared contract per plugin kind: what core code calls, and nothing else.

Each contract is a ``typing.Protocol``: its annotated attributes and its public
methods are what a part of that kind must provide. :func:`check` holds a class
(at ``@register``) or a built instance (when a recipe builds it) against its
kind's contract and raises one :class:`~ddp.errors.PluginError` line naming
the first missing member, or a method whose parameters cannot take the call
core makes. Core code calls only these members, never a probe with getattr.

TensorDict keys: detectors and trackers are TensorDict modules whose keys are
named by role (``key(role)``, renamable with ``set_keys``): a detector writes
its ``"ood"`` role ([B] bool), a tracker its ``"offsets"`` role ([B, K, 3]
metres per tracked object; K is how many objects the controller tracks).
What they read is theirs to declare in ``in_keys``: the env's observation,
and what the controller writes before calling them: ``("ddp", "discrepancy")``
[B] for the detector, ``("ddp", "episode_key")`` [B] (int64: the episode's random key, from the
controller's seed and the episode's; a part that draws at random keys its draws by it, so they do not
depend on the batch) for both, and, when there is a tracker, ``("ddp", "recovered")``
[B, K] (objects already recovered) for the detector too (the tracker runs first).
"""

from __future__ import annotations

import inspect
import typing
from typing import Any, Protocol, runtime_checkable

import torch

from ddp.errors import PluginError


class Encoder(Protocol):
    """Built as ``factory(config, agent_pos_dim=D, point_dim=C)``; E_psi."""

    out_dim: int  # latent size per observation step
    # optional: ``point_dims`` (int), how many leading latent dims are point-cloud features (detectors
    # can score them alone); an encoder without it counts as 0 (unknown)

    def encode(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """``[*, P, C], [*, D] -> [*, out_dim]``."""


class Denoiser(Protocol):
    """Built as ``factory(config, input_dim=, global_cond_dim=[, local_cond_dim=])``. Optional: an int
    ``length_multiple``, which every sequence length T must be a multiple of (checked against the recipe's
    horizon and action steps when the model is built)."""

    def predict(self, sample, timestep, global_cond, local_cond=None) -> torch.Tensor:
        """The network's prediction for ``sample`` [B, T, input_dim] at ``timestep``."""


class Scheduler(Protocol):
    """A diffusion / flow process: the training loss and the sampling loop.

    ``generator`` is None, one ``torch.Generator``, or a list of them, one per row of the batch (the
    controller's per-episode streams, :mod:`ddp.rng`): draw noise through :func:`ddp.schedulers.base.randn`
    (or ``rand`` / ``randint``), which takes all three forms."""

    def loss(self, model_fn, x0, *, generator=None) -> torch.Tensor: ...

    def sample(self, model_fn, noise, *, generator=None) -> torch.Tensor: ...


class Dataset(Protocol):
    """Built as ``factory(config, task=, seed=, env=)``; the demonstrations."""

    def load(self) -> Any:
        """The demonstrations as :class:`ddp.data.episodes.Episodes`."""


class Detector(Protocol):
    """Decides OOD per environment: writes its ``"ood"`` key role ([B] bool). ``in_keys`` / ``out_keys``
    declare what it reads and writes (a real robot refuses a part reading ``("privileged", ...)`` keys)."""

    in_keys: list
    out_keys: list
    sticky: bool  # True: once OOD, stay until recovery and a D_R-I re-check; False: re-decided every cycle
    needs_discrepancy: bool  # True: the controller must forecast every cycle so D_R-I exists

    # optional: ``decides = False`` for a detector that does not decide OOD from observations (``never``,
    # ``substitution``): evaluation then reports no detection metrics for its protocols (default True)

    def forward(self, td): ...

    def key(self, role: str): ...

    def reset(self) -> None: ...


class NeedMoreEpisodes(ValueError):
    """Raised by :meth:`Calibratable.calibrate` when the episodes it got cannot set its threshold yet
    (e.g. too few successful ones): ``more`` is its estimate of how many further ID episodes it needs.
    ``ddp eval`` then rolls out that many more (new seeds, up to ``eval.max_calibration_episodes`` in
    all) and calls ``calibrate`` again with every episode so far, in the order they were run. ``at_least``
    (optional): the fewest episodes in all that could ever do, were every one of them to succeed; a cap
    below it fails at once instead of after rolling out to the cap."""

    def __init__(self, message: str, more: int, at_least: int | None = None):
        super().__init__(message)
        self.more = max(1, int(more))
        self.at_least = at_least


@runtime_checkable
class Calibratable(Protocol):
    """A detector whose threshold is calibrated from ID rollouts (``ddp eval`` does it when it is unset)."""

    needs_calibration: bool

    def calibrate(self, episodes, *, point_dims: int = 0) -> float:
        """Fit on ID episodes (dicts with ``latent_real`` / ``latent_pred`` arrays [chunks, M, D] and
        ``success``); return tau, or raise :class:`NeedMoreEpisodes`."""

    def calibration(self) -> dict: ...

    def load_calibration(self, calibration: dict) -> None: ...


class Tracker(Protocol):
    """How far each tracked object moved: writes its ``"offsets"`` key role ([B, K, 3]); ``in_keys`` /
    ``out_keys`` as for :class:`Detector`. Optionally a ``"visible"`` role ([B, K] bool, ``key("visible")``
    raising KeyError where there is none): which objects it measured this cycle, so that an object seen back
    at its place (offset 0) is told from one it cannot see (without it, a zero offset reads "not seen")."""

    in_keys: list
    out_keys: list

    def forward(self, td): ...

    def key(self, role: str): ...

    def reset(self) -> None: ...


class Recovery(Protocol):
    """Undoes a tracking shift at a subtask's end."""

    trigger_chunk: int | None  # None: the subtasks' triggers end subtasks; an int overrides them (a fixed chunk)

    def recover(self, offsets, displaced, target) -> tuple:
        """``(ee_shift [3], recovered mask [K])`` for the objects in ``displaced`` (and the subtask's target)."""

    def reset(self) -> None: ...


class Trigger(Protocol):
    """When a subtask has ended. ``fired`` may take an optional keyword ``state``: then the controller passes a
    dict of its own per environment, empty when the subtask starts, for a trigger that needs memory (an edge
    rather than a level); it is called every cycle of the subtask, from its first (``subtask_chunks`` 0)."""

    def fired(self, obs, chunk_index: int, subtask_chunks: int) -> bool: ...


class Env(Protocol):
    """A TorchRL env (``EnvBase``) producing ``point_cloud`` [task.num_points, task.point_dim] and ``agent_pos``.

    Optional, on its config dataclass: ``held_out_initial_states(block=0) -> dict``, config overrides under
    which its resets draw none of the initial states this config's resets draw (for an env whose states
    repeat across seeds); a detector's calibration rollouts use them unless ``eval.calibration_env`` is set.
    With ``initial_states_per_draw`` (an int: seeds that far apart repeat a state), calibration seeds move to
    ``block`` 1, 2, ... every that many seeds, each block a draw that repeats none of the others.
    ``simulator_truth() -> bool``: False where the ``("privileged", ...)`` keys (object displacements,
    occlusion) carry no truth (a real robot); detectors and trackers that read them are then refused.
    ``judges_success() -> bool``: False where the env's ``success`` flag means nothing (a real robot: a person
    judges); evaluations then report success as not judged (None), not as 0 %.
    Optional, on the env itself: ``episode_seed`` (int), the seed of the current episode; ``ChunkedEnv`` passes it on
    and the controller keys the episode's random streams by it (without it, by the order episodes start in).
    """

    action_hold: Any  # ddp.safety.HoldSpec: how its actions hold still (controller.on_nonfinite: hold)

    def shift_end_effector(self, delta, *, safe_lift: float = 0.0):
        """Move the end-effector by ``delta`` (metres, 3) outside the episode's step count; the applied shift."""

    def set_seed(self, seed): ...

    def reset(self, *args, **kwargs): ...

    def step(self, tensordict): ...


class EvaluationProtocol(Protocol):
    """What ``get_protocol`` returns: an :class:`ddp.protocols.base.EvalProtocol` (env overrides + controller)."""

    env: dict
    env_if_supported: dict
    detector: dict | None
    imagine: bool | None
    tracker: bool
    occlusion: bool
    env_tracking: bool


#: kind -> its contract
CONTRACTS: dict[str, type] = {
    "encoder": Encoder,
    "denoiser": Denoiser,
    "scheduler": Scheduler,
    "dataset": Dataset,
    "detector": Detector,
    "tracker": Tracker,
    "recovery": Recovery,
    "trigger": Trigger,
    "env": Env,
    "protocol": EvaluationProtocol,
}

#: how core calls each method: (positional args, keyword args) that the signature must accept
_CALLS: dict[tuple[str, str], tuple[int, tuple[str, ...]]] = {
    ("env", "shift_end_effector"): (1, ("safe_lift",)),
    ("recovery", "recover"): (3, ()),
    ("trigger", "fired"): (3, ()),
    ("encoder", "encode"): (2, ()),
    ("dataset", "load"): (0, ()),
    ("detector", "forward"): (1, ()),
    ("detector", "key"): (1, ()),
    ("detector", "reset"): (0, ()),
    ("tracker", "forward"): (1, ()),
    ("tracker", "key"): (1, ()),
    ("tracker", "reset"): (0, ()),
    ("scheduler", "loss"): (2, ("generator",)),
    ("scheduler", "sample"): (2, ("generator",)),
}


def members(contract: type) -> tuple[list[str], list[str]]:
    """(attributes, methods) a contract declares."""
    attributes = [n for n in typing.get_type_hints(contract) if not n.startswith("_")]
    methods = [n for n, v in vars(contract).items() if callable(v) and not n.startswith("_")]
    return attributes, methods


def _accepts(fn, positional: int, keywords: tuple[str, ...]) -> bool:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return True  # builtins without a signature: cannot tell, do not refuse
    params = list(sig.parameters.values())
    if params and params[0].name == "self":
        params = params[1:]
    if any(p.kind is p.VAR_POSITIONAL for p in params):
        positional_ok = True
    else:
        positional_ok = sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params) >= positional
    names = {p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    var_kw = any(p.kind is p.VAR_KEYWORD for p in params)
    required_extra = [p for p in params[positional:] if p.default is p.empty
                      and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in keywords]
    return positional_ok and (var_kw or all(k in names for k in keywords)) and not required_extra


def check(kind: str, obj, *, name: str, module: str | None = None) -> None:
    """Raise one PluginError line if ``obj`` (a class or an instance) lacks a member of ``kind``'s contract."""
    contract = CONTRACTS.get(kind)
    if contract is None:
        return
    where = f"{kind} '{name}'" + (f" ({module})" if module else "")
    attributes, methods = members(contract)
    # a class is checked for its methods (attributes may be set in __init__); a built part for everything
    for attr in [] if isinstance(obj, type) else attributes:
        if not hasattr(obj, attr):
            raise PluginError(f"{where} lacks the attribute '{attr}' that the {kind} contract requires "
                              f"(ddp.contracts.{contract.__name__})")
    for method in methods:
        fn = getattr(obj, method, None)
        if not callable(fn):
            raise PluginError(f"{where} lacks the method '{method}()' that the {kind} contract requires "
                              f"(ddp.contracts.{contract.__name__})")
        call = _CALLS.get((kind, method))
        if call is not None and not _accepts(fn, *call):
            n, kws = call
            wanted = ", ".join([f"{n} positional argument(s)"] + [f"keyword '{k}'" for k in kws])
            raise PluginError(f"{where}: {method}() must accept {wanted}, as core calls it "
                              f"(ddp.contracts.{contract.__name__})")
