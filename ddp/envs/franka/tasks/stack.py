"""Stack Blocks (paper: "Hard | 2 Subtasks, 2 OOD Targets").

"The robot picks up a pink block and places it atop a green base block.
Success requires the pink block to remain perfectly stable and balanced
after the gripper releases."

* Objects: ``pink`` (4 cm cube, 50 g) and ``green`` (5 cm cube, 250 g), the
  sizes of robosuite's Stack and of the franky-sim stack scene.
* ID layout: each block uniformly on its own 10 cm line along x
  (pink at y = -0.10, green at y = +0.10, x in [0.45, 0.55]).
* Subtasks: (0) pick the pink block -- ends at gripper closure
  (``gripper_closure`` trigger); (1) place it on the green block.
* OOD: the pink block is moved 15 cm further out (y -0.15) at chunk 2, while
  the arm approaches it; the green block 15 cm the other way (y +0.15) at
  chunk 7, while the pink block is carried; both land fully outside their
  ID zones. (The scripted oracle closes the gripper at step ~31 and releases
  the block at ~77; with ``oracle_tracking`` the arm carries the pink block
  back by -delta at chunk 6.)
* Success: the pink block lies on the green one (centres within 2 cm in xy,
  its bottom on the green top within 6 mm), touches neither finger, and
  moves slower than 2 cm/s, for 3 consecutive steps.
"""

from __future__ import annotations

import numpy as np

from ddp.envs.disturbances import Displacement
from ddp.envs.franka.tasks.base import DOWN, FrankaTask, Waypoint, WaypointOracle, down, inertial, jitter, uniform

PINK_HALF = 0.02
GREEN_HALF = 0.025


class StackTask(FrankaTask):
    name = "stack"
    object_names = ("pink", "green")
    id_lines = {
        "pink": ((0.45, -0.10, PINK_HALF), (0.55, -0.10, PINK_HALF)),
        "green": ((0.45, 0.10, GREEN_HALF), (0.55, 0.10, GREEN_HALF)),
    }
    footprint = {"pink": PINK_HALF, "green": GREEN_HALF}
    displacements = (
        Displacement(("pink",), (0.0, -0.15, 0.0), chunk=2, tracking="two_stage", snap_back_chunk=6),
        Displacement(("green",), (0.0, 0.15, 0.0), chunk=7),
    )
    max_episode_steps = 160
    subtasks = ("pick the pink block (ends at gripper closure)", "place it on the green block")
    info_keys = ("xy_error", "height")
    oracle_version = 2

    def mjcf(self) -> tuple[str, str]:
        bodies = f"""
<body name="ddp_pink" pos="0.3 -0.1 1.0"><freejoint name="ddp_pink_joint"/>{inertial(0.05, [PINK_HALF] * 3)}
  <geom name="ddp_pink_geom" type="box" size="{PINK_HALF} {PINK_HALF} {PINK_HALF}" rgba="0.95 0.45 0.7 1"
        friction="1.5 0.02 0.001" group="3" condim="4"/></body>
<body name="ddp_green" pos="0.3 0.1 1.0"><freejoint name="ddp_green_joint"/>{inertial(0.25, [GREEN_HALF] * 3)}
  <geom name="ddp_green_geom" type="box" size="{GREEN_HALF} {GREEN_HALF} {GREEN_HALF}" rgba="0.2 0.75 0.3 1"
        friction="1.5 0.02 0.001" group="3" condim="4"/></body>
"""
        return "", bodies

    def new_state(self) -> dict:
        return {"stable_steps": 0}

    def stacked(self, sim) -> bool:
        pink, green = sim.body_position("ddp_pink"), sim.body_position("ddp_green")
        on_top = (
            np.linalg.norm(pink[:2] - green[:2]) < 0.02
            and abs((pink[2] - PINK_HALF) - (green[2] + GREEN_HALF)) < 0.006
        )
        if not on_top:
            return False
        released = not any(sim.touching_gripper(0))
        still = np.linalg.norm(sim.body_velocity("ddp_pink")) < 0.02
        return bool(released and still)

    def update(self, sim, state: dict) -> None:
        state["stable_steps"] = state["stable_steps"] + 1 if self.stacked(sim) else 0

    def success(self, sim, state: dict) -> bool:
        return state["stable_steps"] >= 3

    def info(self, sim, state: dict) -> dict[str, float]:
        pink, green = sim.body_position("ddp_pink"), sim.body_position("ddp_green")
        return {"xy_error": float(np.linalg.norm(pink[:2] - green[:2])), "height": float(pink[2] - green[2])}

    def oracle(self, *, id_frame: bool = False, variance: bool = True) -> WaypointOracle:
        def plan(obs, rng):
            grasp = jitter(rng, [0.006, 0.004, 0.0], 3) + [0.0, 0.0, uniform(rng, 0.0, 0.006)]
            hover = uniform(rng, 0.08, 0.13)
            carry = uniform(rng, 0.10, 0.15)
            place = jitter(rng, [0.004, 0.004, 0.0], 3)
            grasp_yaw, place_yaw = uniform(rng, -0.3, 0.3), uniform(rng, -0.25, 0.25)
            approach = down(grasp_yaw, *jitter(rng, [0.08, 0.08], 2))  # tilted in free space only
            carrying = down(place_yaw, *jitter(rng, [0.06, 0.06], 2))
            pink = lambda o: o.objects[0]  # noqa: E731
            green = lambda o: o.objects[1]  # noqa: E731
            drop = PINK_HALF + GREEN_HALF + 0.006  # pink centre above the green centre when released
            return [
                Waypoint(lambda o: pink(o) + grasp + [0, 0, hover], -1.0, rot=lambda o: approach, tol=0.015,
                         name="above"),
                Waypoint(lambda o: pink(o) + grasp, -1.0, rot=lambda o: down(grasp_yaw), tol=0.008, hold=1,
                         name="descend"),
                Waypoint(None, 1.0, hold=int(uniform(rng, 6, 9)), tol=1.0, name="close"),
                Waypoint(lambda o: np.array([o.anchor[0], o.anchor[1], carry]), 1.0, tol=0.02, name="lift"),
                Waypoint(lambda o: green(o) + place + [0, 0, carry], 1.0, rot=lambda o: carrying, tol=0.015,
                         name="over"),
                Waypoint(lambda o: green(o) + place + [0, 0, drop], 1.0, rot=lambda o: down(place_yaw), tol=0.006,
                         hold=1, speed=0.01, name="lower"),
                Waypoint(None, -1.0, hold=int(uniform(rng, 3, 6)), tol=1.0, name="release"),
                Waypoint(lambda o: o.anchor + [0, 0, 0.03], -1.0, tol=0.05, name="retreat"),
                Waypoint(lambda o: np.array([o.anchor[0], o.anchor[1], carry + 0.05]), -1.0, rot=lambda o: DOWN,
                         tol=0.05, name="up"),
            ]

        return WaypointOracle(plan, id_frame=id_frame, variance=variance)
