"""DreamDiffusionPolicy: a shared encoder feeding a diffusion policy and a diffusion world model.

Training follows the paper's Algorithm 1: the M history observations and the
N future observations are encoded by the SAME encoder E_psi, the policy
denoises the H-step action chunk conditioned (FiLM) on the history latents,
the world model denoises the N future latents conditioned on the history
latents (repeated and concatenated channel-wise) and on the executed actions
a_{M-1 .. M+N-2} (FiLM), and L = L_BC + lambda * L_WM updates all three.
With the world model disabled this is exactly DP3.
"""

from __future__ import annotations

import math

from typing import Any

import torch
from tensordict import TensorDict

from ddp.keys import KeyedModule
from ddp.models.normalizer import MinMaxNormalizer
from ddp.schedulers.base import randn

#: the batch key holding each window step's row in the training frames (read with ``target_refresh_every``)
FRAME_INDEX = "frame_index"


class DreamDiffusionPolicy(KeyedModule):
    """Encoder E_psi + policy pi_theta + world model W_phi (optional) + normaliser.

    TensorDict interface (``forward``): reads ``point_cloud`` [*, M, P, C] and
    ``agent_pos`` [*, M, D] (the M most recent observations), writes
    ``latent`` [*, M, latent_dim], ``action_chunk`` [*, H, A] (the whole
    denoised horizon) and ``action`` [*, N, A] (the chunk to execute).
    """

    default_in_keys = {"point_cloud": "point_cloud", "agent_pos": "agent_pos"}
    default_out_keys = {"latent": "latent", "action_chunk": "action_chunk", "action": "action"}

    def __init__(
        self,
        *,
        encoder: torch.nn.Module,
        policy_net: torch.nn.Module,
        policy_scheduler: Any,
        world_model_net: torch.nn.Module | None,
        world_model_scheduler: Any | None,
        action_dim: int,
        agent_pos_dim: int,
        point_dim: int = 3,
        horizon: int = 16,
        obs_steps: int = 2,
        action_steps: int = 8,
        world_model_weight: float = 1.0,
        world_model_target_gradient: bool = True,
        world_model_batch_fraction: float = 1.0,
        world_model_target_refresh_every: int = 0,
    ):
        super().__init__()
        self.encoder = encoder
        self.policy_net = policy_net
        self.policy_scheduler = policy_scheduler
        self.world_model_net = world_model_net
        self.world_model_scheduler = world_model_scheduler
        # every point channel is normalised (xyz, and rgb when point_dim is 6)
        self.normalizer = MinMaxNormalizer({"action": action_dim, "agent_pos": agent_pos_dim, "point_cloud": point_dim})
        self.action_dim = action_dim
        self.agent_pos_dim = agent_pos_dim
        self.point_dim = point_dim
        self.horizon = horizon
        self.obs_steps = obs_steps
        self.action_steps = action_steps
        self.world_model_weight = world_model_weight
        self.world_model_target_gradient = world_model_target_gradient
        if not 0.0 < world_model_batch_fraction <= 1.0:
            raise ValueError(f"world_model_batch_fraction must be in (0, 1]; got {world_model_batch_fraction}")
        self.world_model_batch_fraction = world_model_batch_fraction
        if world_model_target_refresh_every < 0:
            raise ValueError(f"world_model_target_refresh_every must be >= 0; got {world_model_target_refresh_every}")
        if world_model_target_refresh_every and world_model_target_gradient:
            raise ValueError("world_model_target_refresh_every needs world_model_target_gradient=False")
        self.target_refresh_every = world_model_target_refresh_every
        self.target_table: torch.Tensor | None = None  # [frames, latent_dim]: see refresh_target_table
        self.latent_dim = encoder.out_dim

    @property
    def has_world_model(self) -> bool:
        return self.world_model_net is not None

    @property
    def window(self) -> int:
        """Frames per training sample: the policy's horizon and, with a world model, the M + N frames its
        history and future targets span (without one, DP3's and FlowPolicy's windows: the horizon)."""
        return max(self.horizon, self.obs_steps + self.action_steps) if self.has_world_model else self.horizon

    # ------------------------------------------------------------------ encoding
    @property
    def point_dims(self) -> int:
        """How many leading latent dims come from the point cloud (the encoder's optional ``point_dims``; 0:
        unknown or none). Detectors can score that part of the latent alone."""
        return int(getattr(self.encoder, "point_dims", 0))

    def encode(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """O = E_psi(X): raw observations [*, P, C] / [*, D] -> latents [*, latent_dim]."""
        pc = self.normalizer.normalize("point_cloud", point_cloud)
        pos = self.normalizer.normalize("agent_pos", agent_pos)
        return self.encoder.encode(pc, pos)

    @property
    def uses_target_table(self) -> bool:
        """Training looks the world model's future targets up in :attr:`target_table` (``target_refresh_every``)."""
        return self.has_world_model and self.target_refresh_every > 0

    @torch.no_grad()
    def refresh_target_table(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor, frames_per_call: int = 256) -> None:
        """Encode every training frame (``point_cloud`` [F, P, C], ``agent_pos`` [F, D], unnormalised) with the
        current encoder into :attr:`target_table` [F, latent_dim], ``frames_per_call`` frames at a time.

        :meth:`loss` then reads the future targets of a batch that carries ``frame_index`` from the table
        instead of encoding them. The table is overwritten in place (a compiled loss keeps its guards).
        """
        frames = point_cloud.shape[0]
        dev = next(self.parameters()).device
        if self.target_table is None or self.target_table.shape[0] != frames or self.target_table.device != dev:
            self.target_table = torch.empty(frames, self.latent_dim, device=dev)
        for start in range(0, frames, frames_per_call):
            end = min(start + frames_per_call, frames)
            latents = self.encode(point_cloud[start:end].to(dev), agent_pos[start:end].to(dev))
            self.target_table[start:end] = latents.to(self.target_table.dtype)

    # ------------------------------------------------------------------ training (Algorithm 1)
    def loss(self, batch: TensorDict, generator: torch.Generator | None = None) -> TensorDict:
        """The objective's terms, TorchRL style: the ``loss_*`` keys sum to the objective.

        ``loss_bc`` = L_BC, ``loss_wm`` = lambda * L_WM (weighted), ``loss`` = their sum, and the
        detached diagnostic ``wm_error`` = L_WM unweighted (comparable across lambdas).

        ``batch`` holds windows: ``point_cloud`` [B, T, P, C], ``agent_pos``
        [B, T, D] with T >= M + N (T >= M without a world model) and
        ``action`` [B, H, A], all unnormalised. With ``target_refresh_every`` the batch also carries
        ``frame_index`` [B, T] (each window step's row in the training frames) and the future targets
        are rows of :attr:`target_table` (see :meth:`refresh_target_table`), not encoded here.
        """
        M, N, H = self.obs_steps, self.action_steps, self.horizon
        pc, pos, act = batch[self.key("point_cloud")], batch[self.key("agent_pos")], batch["action"]
        n_obs = M + N if self.has_world_model else M
        if pc.shape[1] < n_obs or act.shape[1] < H:
            raise ValueError(
                f"batch windows too short: need {n_obs} observations and {H} actions, "
                f"got {pc.shape[1]} and {act.shape[1]}"
            )
        # 2. Encode observations: history O_{0..M-1} and future O_{M..M+N-1}, one shared E_psi.
        #    With world_model_batch_fraction < 1 only the first Bw samples' future frames are encoded.
        B = pc.shape[0]
        # rounded before the ceiling: 0.07 x 100 is 7.000000000000001 in floats (8 samples, not 7)
        Bw = B if self.world_model_batch_fraction >= 1.0 else max(1, math.ceil(round(self.world_model_batch_fraction
                                                                                       * B, 9)))
        if self.uses_target_table:
            if self.target_table is None or FRAME_INDEX not in batch.keys():
                raise RuntimeError("world_model.target_refresh_every > 0: the loss needs the batch's 'frame_index' "
                                   "and a target table (refresh_target_table; ddp train does both)")
            history = self.encode(pc[:, :M], pos[:, :M])
            future = self.target_table[batch[FRAME_INDEX][:Bw, M:n_obs]].to(history.dtype)
        elif self.has_world_model and (not self.world_model_target_gradient or Bw < B):
            history = self.encode(pc[:, :M], pos[:, :M])
            with torch.set_grad_enabled(self.world_model_target_gradient and torch.is_grad_enabled()):
                future = self.encode(pc[:Bw, M:n_obs], pos[:Bw, M:n_obs])
        else:
            latents = self.encode(pc[:, :n_obs], pos[:, :n_obs])
            history, future = latents[:, :M], latents[:, M:n_obs]
        actions = self.normalizer.normalize("action", act[:, :H])

        # 3. Diffusion policy loss L_BC, conditioned (FiLM) on the history latents.
        history_cond = history.flatten(1)
        loss_bc = self.policy_scheduler.loss(
            lambda x, t: self.policy_net.predict(x, t, history_cond), actions, generator=generator
        )
        out = {"loss_bc": loss_bc}
        if self.has_world_model:
            # 4. World-model loss L_WM: future latents, conditioned on history (channel concat)
            #    and on the executed actions a_{M-1 .. M+N-2} (FiLM).
            executed = actions[:Bw, M - 1 : M - 1 + N].flatten(1)
            wm_cond = history_cond[:Bw]
            loss_wm = self.world_model_scheduler.loss(
                lambda x, t: self.world_model_net.predict(x, t, executed, wm_cond), future, generator=generator
            )
            # 5. L_total = L_BC + lambda * L_WM: the weighted term is the loss_* key
            out["loss_wm"] = self.world_model_weight * loss_wm
            out["wm_error"] = loss_wm.detach()
        else:
            out["loss_wm"] = torch.zeros_like(loss_bc)
            out["wm_error"] = torch.zeros_like(loss_bc).detach()
        out["loss"] = sum(v for k, v in out.items() if k.startswith("loss_"))
        return TensorDict(out, batch_size=[])

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def sample_actions(self, history: torch.Tensor, generator=None) -> torch.Tensor:
        """a_{0..H-1} ~ pi_theta(. | O_{0..M-1}): latents [*, M, L] -> unnormalised actions [*, H, A].

        ``generator``: one ``torch.Generator``, one per row of the flattened batch, or None."""
        batch_shape = history.shape[:-2]
        cond = history.reshape(-1, self.obs_steps * self.latent_dim)
        noise = randn((cond.shape[0], self.horizon, self.action_dim), generator=generator, device=cond.device,
                      dtype=cond.dtype)
        actions = self.policy_scheduler.sample(
            lambda x, t: self.policy_net.predict(x, t, cond), noise, generator=generator
        )
        return self.normalizer.unnormalize("action", actions).reshape(*batch_shape, self.horizon, self.action_dim)

    def executed_actions(self, action_chunk: torch.Tensor) -> torch.Tensor:
        """The N actions that are executed: a_{M-1 .. M+N-2} of the denoised horizon."""
        start = self.obs_steps - 1
        return action_chunk[..., start : start + self.action_steps, :]

    @torch.no_grad()
    def imagine(
        self, history: torch.Tensor, actions: torch.Tensor, generator=None
    ) -> torch.Tensor:
        """O_{M..M+N-1} ~ W_phi(. | O_{0..M-1}, a): latents [*, M, L] + actions [*, N, A] -> [*, N, L].

        ``generator``: one ``torch.Generator``, one per row of the flattened batch, or None."""
        if not self.has_world_model:
            raise RuntimeError("this model has no world model (world_model.enabled is false)")
        batch_shape = history.shape[:-2]
        cond = history.reshape(-1, self.obs_steps * self.latent_dim)
        executed = self.normalizer.normalize("action", actions).reshape(cond.shape[0], -1)
        noise = randn((cond.shape[0], self.action_steps, self.latent_dim), generator=generator, device=cond.device,
                      dtype=cond.dtype)
        future = self.world_model_scheduler.sample(
            lambda x, t: self.world_model_net.predict(x, t, executed, cond), noise, generator=generator
        )
        return future.reshape(*batch_shape, self.action_steps, self.latent_dim)

    def forward(self, tensordict: TensorDict) -> TensorDict:
        latent = self.encode(tensordict[self.key("point_cloud")], tensordict[self.key("agent_pos")])
        chunk = self.sample_actions(latent[..., -self.obs_steps :, :])
        tensordict.set(self.key("latent"), latent)
        tensordict.set(self.key("action_chunk"), chunk)
        tensordict.set(self.key("action"), self.executed_actions(chunk))
        return tensordict
