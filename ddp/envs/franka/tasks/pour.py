"""Pour Tea (paper: "Medium | 2 Subtasks, 1 OOD Target").

"The robot grasps a teapot, navigates to a cup, executes a pouring motion,
and returns the teapot to the table. Success requires the spout to remain
precisely aligned with the cup's center during the entire pour."

Modelled with small balls as tea:

* Objects: ``cup`` (an open 8 x 8 x 6 cm box cup, 400 g) and ``teapot`` (a
  6 x 6 x 7 cm pot (100 g), lidded on its handle half, open on its spout half, with
  a spout edge on the -y wall and a vertical plate handle on the +y side that
  the gripper grasps from above); ``TEA_BALLS`` balls (1.4 cm, 3 g) start
  inside the pot.
* ID layout: the cup uniformly on a 10 cm line along x (y = -0.10, x in
  [0.45, 0.55]); the teapot at (0.50, 0.12).
* Subtasks: (0) grasp the teapot -- ends at gripper closure
  (``gripper_closure``); (1) carry it to the cup and pour -- ends after an
  allotted time (``timer``), before the teapot is carried back.
* OOD: the cup is moved 15 cm further out (y -0.15) at chunk 6, while the
  lifted teapot travels toward it (fully outside its ID zone). The scripted
  oracle (version 3, seeds 0-2) closes the gripper at steps 35-37, tilts from
  69-74, untilts from 109-116 and starts carrying the pot back at 131-139, so
  a ``timer`` of 12 chunks after the closure chunk (5) ends the pouring
  subtask at chunk 17 (step 136): after the pour and before the set-down,
  mid-untilt on some seeds; ``oracle_tracking`` snaps back then too.
* Pouring: the pot is tilted about the base x axis (spout down) by ~115
  degrees with the spout edge over the cup; the balls leave over the spout
  edge.
* Success: at least ``MIN_BALLS`` balls rest inside the cup, and the teapot
  is back upright on the table within 4 cm of where it started, released
  (touching neither finger) and at rest.
"""

from __future__ import annotations

import numpy as np

from ddp.envs.disturbances import Displacement
from ddp.envs.franka.control import quat_to_mat
from ddp.envs.franka.tasks.base import (
    DOWN, FrankaTask, Waypoint, WaypointOracle, down, inertial, jitter, rot_x, uniform,
)

TEA_BALLS = 6
MIN_BALLS = 4  # "enough tea in the cup"
BALL_RADIUS = 0.007
# teapot (root frame at the centre of its base, z up; spout toward -y, handle toward +y)
POT_INNER = 0.03  # inner half width (x and y)
POT_WALL = 0.004
POT_HEIGHT = 0.07
POT_FLOOR = 0.005
LID_FROM = -0.002  # the lid covers y in [LID_FROM, POT_INNER + POT_WALL]: the spout half stays open
HANDLE_Y = POT_INNER + POT_WALL + 0.054  # handle plate centre: the open gripper (8 cm) straddles it
HANDLE_HALF = (0.025, 0.015, 0.025)  # 3 cm thick: the closing fingers squeeze it hard
HANDLE_Z = 0.045  # handle plate centre height
GRASP = np.array([0.0, HANDLE_Y, HANDLE_Z + 0.004])  # end-effector point on the handle (root frame)
SPOUT_EDGE = np.array([0.0, -(POT_INNER + POT_WALL), POT_HEIGHT])  # where the tea leaves the pot
# cup (root frame at the centre of its base)
CUP_INNER = 0.04
CUP_WALL = 0.005
CUP_HEIGHT = 0.06
TEAPOT_HOME = (0.50, 0.12, 0.0)
POUR_ANGLE = np.radians(115.0)
UNTILT_RISE = 0.06  # metres the pot rises while it turns back upright after pouring
POUR_LEAD = 0.03


def _box(name, half, pos, rgba, **extra) -> str:
    attrs = " ".join(f'{k}="{v}"' for k, v in extra.items())
    return (f'<geom name="{name}" type="box" size="{half[0]:.4f} {half[1]:.4f} {half[2]:.4f}" '
            f'pos="{pos[0]:.4f} {pos[1]:.4f} {pos[2]:.4f}" rgba="{rgba}" group="3" {attrs}/>')  # fmt: skip


class PourTask(FrankaTask):
    name = "pour"
    object_names = ("cup", "teapot")
    id_lines = {"cup": ((0.45, -0.10, 0.0), (0.55, -0.10, 0.0))}
    fixed = {"teapot": TEAPOT_HOME}
    footprint = {"cup": CUP_INNER + CUP_WALL, "teapot": POT_INNER + POT_WALL}
    displacements = (
        Displacement(("cup",), (0.0, -0.15, 0.0), chunk=6, tracking="two_stage", snap_back_chunk=17),
    )
    max_episode_steps = 240
    subtasks = ("grasp the teapot (ends at gripper closure)", "pour into the cup (ends after an allotted time)")
    info_keys = ("balls_in_cup", "teapot_returned")
    oracle_version = 3  # 3: the pot rises while it untilts and does not linger (the post-pour pose differs)

    def mjcf(self) -> tuple[str, str]:
        i, w, h, f = POT_INNER, POT_WALL, POT_HEIGHT, POT_FLOOR
        pot_rgba, lid_rgba = "0.55 0.75 0.85 1", "0.45 0.65 0.8 1"
        walls = [
            _box("ddp_teapot_floor", (i + w, i + w, f / 2), (0, 0, f / 2), pot_rgba),
            _box("ddp_teapot_wall_xp", (w / 2, i + w, h / 2), (i + w / 2, 0, h / 2), pot_rgba),
            _box("ddp_teapot_wall_xn", (w / 2, i + w, h / 2), (-i - w / 2, 0, h / 2), pot_rgba),
            _box("ddp_teapot_wall_yp", (i, w / 2, h / 2), (0, i + w / 2, h / 2), pot_rgba),
            _box("ddp_teapot_wall_yn", (i, w / 2, h / 2), (0, -i - w / 2, h / 2), pot_rgba),
            _box("ddp_teapot_lid", (i, (i + w - LID_FROM) / 2, w / 2), (0, (i + w + LID_FROM) / 2, h + w / 2),
                 lid_rgba),
            # handle: a vertical plate on two bridges, grasped across its thickness
            _box("ddp_teapot_handle", HANDLE_HALF, (0, HANDLE_Y, HANDLE_Z), "0.3 0.3 0.35 1",
                 friction="2 0.05 0.001"),
            _box("ddp_teapot_bridge_p", (0.004, (HANDLE_Y - i - w) / 2, 0.006),
                 (0.021, (HANDLE_Y + i + w) / 2, HANDLE_Z + 0.012), "0.3 0.3 0.35 1"),
            _box("ddp_teapot_bridge_n", (0.004, (HANDLE_Y - i - w) / 2, 0.006),
                 (-0.021, (HANDLE_Y + i + w) / 2, HANDLE_Z + 0.012), "0.3 0.3 0.35 1"),
        ]
        ci, cw, ch = CUP_INNER, CUP_WALL, CUP_HEIGHT
        cup_rgba = "0.95 0.95 0.9 1"
        cup = [
            _box("ddp_cup_floor", (ci + cw, ci + cw, cw / 2), (0, 0, cw / 2), cup_rgba),
            _box("ddp_cup_wall_xp", (cw / 2, ci + cw, ch / 2), (ci + cw / 2, 0, ch / 2), cup_rgba),
            _box("ddp_cup_wall_xn", (cw / 2, ci + cw, ch / 2), (-ci - cw / 2, 0, ch / 2), cup_rgba),
            _box("ddp_cup_wall_yp", (ci, cw / 2, ch / 2), (0, ci + cw / 2, ch / 2), cup_rgba),
            _box("ddp_cup_wall_yn", (ci, cw / 2, ch / 2), (0, -ci - cw / 2, ch / 2), cup_rgba),
        ]
        balls = "\n".join(
            f'<body name="ddp_ball{k}" pos="{0.3 + 0.02 * k} 0.5 1.2"><freejoint name="ddp_ball{k}_joint"/>'
            f'<inertial pos="0 0 0" mass="0.003" diaginertia="6e-8 6e-8 6e-8"/>'
            f'<geom name="ddp_ball{k}_geom" type="sphere" size="{BALL_RADIUS}" rgba="0.75 0.5 0.1 1" group="3" '
            f'friction="0.4 0.005 0.0001" solref="0.005 1"/></body>'
            for k in range(TEA_BALLS)
        )
        bodies = f"""
<body name="ddp_cup" pos="0.5 -0.1 1.0"><freejoint name="ddp_cup_joint"/>
  {inertial(0.4, (ci + cw, ci + cw, ch / 2), (0, 0, ch / 2))}
  {"".join(cup)}
</body>
<body name="ddp_teapot" pos="0.5 0.12 1.0"><freejoint name="ddp_teapot_joint"/>
  {inertial(0.1, (i + w, i + w, h / 2), (0, 0.01, h / 2))}
  {"".join(walls)}
</body>
{balls}
"""
        return "", bodies

    # ------------------------------------------------------------- scene
    def place(self, sim, layout, rng) -> None:
        super().place(sim, layout, rng)
        pot = np.asarray(layout["teapot"], dtype=np.float64)
        grid = [(-0.015, -0.008), (0.0, -0.008), (0.015, -0.008), (-0.015, 0.008), (0.0, 0.008), (0.015, 0.008)]
        for k in range(TEA_BALLS):
            x, y = grid[k % len(grid)]
            z = POT_FLOOR + BALL_RADIUS + 0.001 + 2 * BALL_RADIUS * (k // len(grid))
            sim.set_body_pose(f"ddp_ball{k}", pot + [x, y, z])

    def balls_in_cup(self, sim) -> int:
        cup = sim.body_position("ddp_cup")
        rot = sim.body_rotation("ddp_cup")
        n = 0
        for k in range(TEA_BALLS):
            p = rot.T @ (sim.body_position(f"ddp_ball{k}") - cup)
            if abs(p[0]) < CUP_INNER and abs(p[1]) < CUP_INNER and CUP_WALL < p[2] < CUP_HEIGHT:
                n += 1
        return n

    def new_state(self) -> dict:
        return {"start": None}

    def update(self, sim, state: dict) -> None:
        if state["start"] is None:
            state["start"] = sim.body_position("ddp_teapot")

    def teapot_returned(self, sim, state: dict) -> bool:
        pot = sim.body_position("ddp_teapot")
        upright = sim.body_rotation("ddp_teapot")[2, 2] > 0.95
        start = state["start"] if state.get("start") is not None else np.asarray(TEAPOT_HOME)
        near = np.linalg.norm(pot[:2] - start[:2]) < 0.04 and pot[2] < 0.01
        released = not any(sim.touching_gripper(1))
        still = np.linalg.norm(sim.body_velocity("ddp_teapot")) < 0.02
        return bool(upright and near and released and still)

    def success(self, sim, state: dict) -> bool:
        return self.balls_in_cup(sim) >= MIN_BALLS and self.teapot_returned(sim, state)

    def info(self, sim, state: dict) -> dict[str, float]:
        return {
            "balls_in_cup": float(self.balls_in_cup(sim)),
            "teapot_returned": float(self.teapot_returned(sim, state)),
        }

    # ------------------------------------------------------------- oracle
    def oracle(self, *, id_frame: bool = False, variance: bool = True) -> WaypointOracle:
        def plan(obs, rng):
            home = obs.objects[1].copy()  # where the teapot starts (and goes back to)
            grasp = GRASP + jitter(rng, [0.006, 0.0, 0.004], 3)
            hover = uniform(rng, 0.06, 0.10)
            carry = uniform(rng, 0.17, 0.20)  # end-effector height while carrying
            low = uniform(rng, 0.015, 0.03)  # spout edge over the cup rim while pouring
            high = 0.09  # ... and before tilting: the pot's base (7 cm below the edge) clears the rim
            angle = POUR_ANGLE + jitter(rng, np.radians(5.0))
            # the tea leaves the edge rolling toward -y: aim the edge LEAD metres short of the cup centre
            aim = jitter(rng, [0.006, 0.005, 0.0], 3) + [0.0, POUR_LEAD, 0.0]
            pour_hold = int(uniform(rng, 12, 18))
            approach = down(uniform(rng, -0.15, 0.15), *jitter(rng, [0.06, 0.06], 2))  # free space only
            lifting = down(uniform(rng, -0.1, 0.1), *jitter(rng, [0.04, 0.04], 2))
            returning = down(uniform(rng, -0.1, 0.1), *jitter(rng, [0.04, 0.04], 2))

            def handle(o):
                return o.objects[1] + quat_to_mat(o.quats[1]) @ grasp

            def edge_in_hand(o):
                """The spout edge in the end-effector frame (measured: follows any slip of the grasp)."""
                edge = o.objects[1] + quat_to_mat(o.quats[1]) @ SPOUT_EDGE
                return o.rot.T @ (edge - o.ee)

            def tilt(rot):
                m = rot @ DOWN.T
                return float(np.arctan2(m[2, 1], m[1, 1]))

            def pour_path(o, rot):
                """Tilt about the spout edge: the edge stays over the cup and sinks as the pot turns."""
                cup = o.objects[0] + aim
                z = CUP_HEIGHT + float(np.interp(tilt(rot), [0.7, 1.4], [high, low]))
                return np.array([cup[0], cup[1], z]) - rot @ edge_in_hand(o)

            def untilt_path(o, rot):
                """Back upright while rising UNTILT_RISE: the pose after the pour is not the one before it,
                which only the few poured balls in the cloud told apart (the policy tilted again)."""
                upright = 1.0 - min(1.0, max(0.0, tilt(rot) / angle))
                return pour_path(o, rot) + [0.0, 0.0, UNTILT_RISE * upright]

            tilted = lambda o: rot_x(angle) @ DOWN  # noqa: E731
            return [
                Waypoint(lambda o: handle(o) + [0, 0, hover], -1.0, rot=lambda o: approach, tol=0.015, name="above"),
                Waypoint(handle, -1.0, rot=lambda o: DOWN, tol=0.006, hold=1, name="descend"),
                Waypoint(None, 1.0, hold=int(uniform(rng, 6, 9)), tol=1.0, name="grasp"),
                Waypoint(lambda o: np.array([o.anchor[0], o.anchor[1], carry]), 1.0, rot=lambda o: lifting, tol=0.02,
                         name="lift"),
                Waypoint(None, 1.0, rot=lambda o: DOWN, path=pour_path, tol=0.012, name="to_cup"),
                Waypoint(None, 1.0, rot=tilted, path=pour_path, tol=0.02, hold=pour_hold, name="pour"),
                Waypoint(None, 1.0, rot=lambda o: DOWN, path=untilt_path, tol=0.02, name="untilt"),
                Waypoint(lambda o: home + grasp + [0, 0, carry - grasp[2]], 1.0, rot=lambda o: returning,
                         tol=0.015, name="back"),
                Waypoint(lambda o: home + grasp + [0, 0, 0.004], 1.0, rot=lambda o: DOWN, tol=0.006, speed=0.01,
                         hold=1, name="set"),
                Waypoint(None, -1.0, hold=int(uniform(rng, 4, 7)), tol=1.0, name="release"),
                Waypoint(lambda o: o.anchor + [0, 0, 0.08], -1.0, tol=0.03, name="retreat"),
            ]

        return WaypointOracle(plan, id_frame=id_frame, variance=variance, rot_speed=0.09)

