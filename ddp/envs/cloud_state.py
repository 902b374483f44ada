"""The point-cloud observation of a MuJoCo env with one depth camera: render schedule, occlusion, clean-up.

:class:`CloudStateMixin` is what the ``metaworld`` and ``adroit`` envs share:
the last cloud (``_cloud``) and whether it is the occlusion's blind one
(``_occluded``), updated after every action as the paper's protocol says
(blind while ``ddp.envs.disturbances.Occlusion`` covers the step, else
rendered when ``ddp.envs.chunked.render_due`` says so, else unchanged), and
``close()``, which frees the env's renderer and simulator.
"""

from __future__ import annotations

import numpy as np

from ddp.envs.chunked import render_due
from ddp.envs.pointcloud import DepthToCloud

__all__ = ["CloudStateMixin"]


class CloudStateMixin:
    """Point-cloud state and clean-up of a MuJoCo TorchRL env; list it before ``EnvBase``.

    The env provides ``config`` (``render_point_cloud``, ``image_size``,
    ``crop_min``, ``crop_max``, ``num_points``, ``obs_every``, ``obs_history``,
    ``chunk_len``), ``sim`` (with ``.model`` and ``.data``), ``_renderer`` (a
    ``SceneRenderer``), ``_cam`` (the cloud camera's id), ``_occlusion_plan``
    (an ``Occlusion`` or None) and ``_rng``; it calls ``_init_cloud`` in its
    constructor once ``_cam`` is set, ``_reset_cloud`` at reset and
    ``_update_cloud(t)`` after each action.
    """

    def _init_cloud(self) -> None:
        """Build the depth-to-cloud projection for the camera's field of view; start with an all-zero cloud."""
        cfg = self.config
        self._cloud_fn = None
        if cfg.render_point_cloud:
            self._cloud_fn = DepthToCloud(
                cfg.image_size, cfg.image_size, float(self.sim.model.cam_fovy[self._cam]),
                cfg.crop_min, cfg.crop_max, cfg.num_points,
            )  # fmt: skip
        self._cloud = np.zeros((cfg.num_points, 3), dtype=np.float32)
        self._occluded = False

    def _reset_cloud(self) -> None:
        """At reset: the camera sees again; render the first cloud."""
        self._occluded = False
        if self.config.render_point_cloud:
            self._cloud = self._render_cloud()

    def _update_cloud(self, t: int) -> None:
        """After ``t`` actions: the occlusion's blind cloud, a new render when due, else the last cloud."""
        cfg = self.config
        if cfg.render_point_cloud:
            occ = self._occlusion_plan
            self._occluded = occ is not None and occ.covers(t, cfg.chunk_len)
            if self._occluded:
                self._cloud = occ.corrupt(cfg.num_points, cfg.crop_min, cfg.crop_max, self._rng)
            elif self._render_due(t):
                self._cloud = self._render_cloud()

    def _render_due(self, t: int) -> bool:
        return render_due(t, self.config.obs_every, self.config.obs_history)

    def _render_cloud(self) -> np.ndarray:
        # data.cam_xpos / cam_xmat follow a re-posed camera after any mj_forward / mj_step (reset runs one)
        data = self.sim.data
        depth = self._renderer.depth(data, self._cam, self.config.image_size)
        return self._cloud_fn(depth, data.cam_xpos[self._cam], data.cam_xmat[self._cam])

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Free the renderers (their EGL contexts) and the simulator."""
        renderer = self.__dict__.get("_renderer")
        if renderer is not None:
            renderer.close()
        sim = self.__dict__.get("sim")
        if sim is not None:
            sim.close()
        super().close(raise_if_closed=raise_if_closed)
