"""Offscreen MuJoCo rendering shared by the MuJoCo envs: EGL set-up, depth-only and colour cameras.

* :func:`use_egl` makes ``mujoco.Renderer`` use EGL when ``MUJOCO_GL=egl``,
  even if mujoco was imported (by torchrl, say) before the variable was set.
* :class:`CloudCamera` is the DP3 cloud of one camera of a
  :class:`SceneRenderer`: depth render, world frame, crop, farthest point
  sampling (what the metaworld and adroit envs observe).
* :class:`MujocoCloudEnv` is the :class:`ddp.envs.base.PointCloudEnv` of a
  MuJoCo simulator ``sim`` (``.model``, ``.data``, ``.close()``) with one
  :class:`CloudCamera`: the adapter part the metaworld and adroit envs share.
* :class:`SceneRenderer` owns the renderers of one model: a depth renderer
  for point clouds (no shadows or multisampling, sites hidden so goal
  markers stay out of the cloud) and colour renderers for videos, one per
  frame size, created on first use. ``close()`` frees their EGL contexts;
  renderers nobody closed are closed at exit, before EGL shuts down, so
  exiting prints no EGL errors.
"""

from __future__ import annotations

import atexit
import os
import weakref

import numpy as np

from ddp.envs.base import PointCloudEnv
from ddp.errors import suggest

__all__ = ["CloudCamera", "MujocoCloudEnv", "SceneRenderer", "use_egl"]

_OPEN: weakref.WeakSet = weakref.WeakSet()
_hook_registered = False


def use_egl() -> None:
    """Swap mujoco's GLContext for the EGL one when ``MUJOCO_GL=egl`` (the default set by ddp's envs)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    if os.environ["MUJOCO_GL"].lower() == "egl":
        from mujoco import gl_context

        if getattr(gl_context, "GLContext", None) is None or gl_context.GLContext.__module__ != "mujoco.egl":
            from mujoco.egl import GLContext

            gl_context.GLContext = GLContext


def _close_open() -> None:
    for renderer in list(_OPEN):
        renderer.close()


def _track(renderer) -> None:
    """Close ``renderer`` at exit if nobody did (``atexit`` runs last-in first-out and MuJoCo
    registers EGL's termination with its first context, so this hook runs before it)."""
    global _hook_registered
    if not _hook_registered:
        atexit.register(_close_open)
        _hook_registered = True
    _OPEN.add(renderer)


# the site group that depth frames show: ``visible_sites`` are moved into it, every other group is hidden
CLOUD_SITE_GROUP = 5


class SceneRenderer:
    """Depth and colour renderers of one ``MjModel`` (created lazily, closed by ``close()``).

    Depth frames (point clouds) hide every site except those named in ``visible_sites`` (e.g. MetaWorld's
    ``goal`` marker: the only sign of a push or place target), which colour frames show as well."""

    def __init__(self, model, visible_sites: tuple[str, ...] = ()):
        import mujoco

        self._mj = mujoco
        self.model = model
        self._depth = None
        self._depth_size: tuple[int, int] | None = None
        self._rgb: dict[tuple[int, int], object] = {}
        self._hide_sites = mujoco.MjvOption()
        self._hide_sites.sitegroup[:] = 0
        self._rgb_option = mujoco.MjvOption()
        if visible_sites:
            names = [model.site(i).name for i in range(model.nsite)]
            for name in visible_sites:
                if name not in names:
                    raise ValueError(f"visible_sites: no site {name!r} in this model{suggest(name, names)}")
                model.site_group[names.index(name)] = CLOUD_SITE_GROUP
            self._hide_sites.sitegroup[CLOUD_SITE_GROUP] = 1
            self._rgb_option.sitegroup[CLOUD_SITE_GROUP] = 1

    def camera_id(self, name: str, what: str = "camera") -> int:
        """The id of a named camera; a one-line error naming the closest camera otherwise."""
        names = [self.model.camera(i).name for i in range(self.model.ncam)]
        if name not in names:
            raise ValueError(f"{what} must be one of {names}; got {name!r}{suggest(name, names)}")
        return names.index(name)

    def _new(self, width: int, height: int):
        vis = self.model.vis.global_
        vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
        renderer = self._mj.Renderer(self.model, height, width)
        _track(renderer)
        return renderer

    def depth(self, data, camera: int, width: int, height: int | None = None) -> np.ndarray:
        """Metric depth ``[height, width]`` from camera id ``camera`` (sites but ``visible_sites`` hidden, no
        shadows)."""
        height = width if height is None else height
        if self._depth is None or self._depth_size != (width, height):
            if self._depth is not None:
                self._depth.close()
            self.model.vis.quality.shadowsize = 0  # depth only: no shadow maps or multisampling
            self.model.vis.quality.offsamples = 0
            self._depth = self._new(width, height)
            self._depth.enable_depth_rendering()
            self._depth_size = (width, height)
        self._depth.update_scene(data, camera=camera, scene_option=self._hide_sites)
        return self._depth.render()

    def rgb(self, data, camera: int, width: int, height: int, upside_down: bool = False) -> np.ndarray:
        """A colour frame ``[height, width, 3]`` uint8. ``upside_down``: the camera is rolled about half a
        turn (its image-up points down), so the frame is turned 180 degrees (a vertical flip alone would
        mirror the scene: a render never is)."""
        key = (width, height)
        if key not in self._rgb:
            self._rgb[key] = self._new(width, height)
        renderer = self._rgb[key]
        renderer.update_scene(data, camera=camera, scene_option=self._rgb_option)
        image = renderer.render()
        return (image[::-1, ::-1] if upside_down else image).copy()

    def close(self) -> None:
        for renderer in [self._depth, *self._rgb.values()]:
            if renderer is not None:
                renderer.close()
        self._depth, self._depth_size, self._rgb = None, None, {}


class CloudCamera:
    """The point cloud one camera of ``renderer`` sees: ``config``'s ``image_size`` square depth image,
    back-projected to the world frame, cropped to ``crop_min`` / ``crop_max``, ``num_points`` by FPS."""

    def __init__(self, renderer: SceneRenderer, camera: int, config):
        from ddp.envs.pointcloud import DepthToCloud

        self.renderer, self.camera, self.size = renderer, camera, config.image_size
        fovy = float(renderer.model.cam_fovy[camera])
        self._to_cloud = DepthToCloud(self.size, self.size, fovy, config.crop_min, config.crop_max, config.num_points)

    def __call__(self, data) -> np.ndarray:
        """Float32 ``[num_points, 3]``; ``data.cam_xpos`` / ``cam_xmat`` follow a re-posed camera after any
        ``mj_forward`` / ``mj_step`` (a reset runs one)."""
        depth = self.renderer.depth(data, self.camera, self.size)
        return self._to_cloud(depth, data.cam_xpos[self.camera], data.cam_xmat[self.camera])


class MujocoCloudEnv(PointCloudEnv):
    """A :class:`PointCloudEnv` whose cloud is one MuJoCo camera's: the subclass sets ``sim``,
    ``_renderer`` (a :class:`SceneRenderer`) and ``_camera`` (a :class:`CloudCamera`, or None when
    ``render_point_cloud`` is off)."""

    def _render_cloud(self) -> np.ndarray:
        return self._camera(self.sim.data)

    def _close_sim(self) -> None:
        for name in ("_renderer", "sim"):  # tolerant of a constructor that failed half-way
            part = self.__dict__.get(name)
            if part is not None:
                part.close()
