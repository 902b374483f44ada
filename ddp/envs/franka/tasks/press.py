"""Press Button (paper: "Easy | 1 Subtask, 1 OOD Target").

"The robot closes its gripper to precisely press a button. Success requires
depressing it exactly to the activation threshold, avoiding both incomplete
contact (under-pressing) and excessive force (over-pressing)."

* Object: ``button``, a fixed 6 x 6 x 3 cm housing with a 3 cm wide cap standing
  2.5 cm above it on a spring-loaded slide joint (2.4 cm travel, 300 N/m).
* ID layout: the button uniformly on a 10 cm line along x (y = 0, x in
  [0.45, 0.55]).
* Subtask: (0) press the button (one subtask, no trigger).
* OOD: the button is moved 15 cm sideways (y +0.15) at chunk 2, fully
  outside its ID zone.
* Success: a press reaches the activation depth (6 mm) without passing the
  over-press depth (14 mm) and the button is released again (depth < 2 mm).
  A press past 14 mm fails the episode for good, after a good press too (the
  env's ``"failed"`` flag revokes the success); a press that stops short can
  be repeated.
"""

from __future__ import annotations

from ddp.envs.disturbances import Displacement
from ddp.envs.franka.tasks.base import DOWN, FrankaTask, Waypoint, WaypointOracle, down, inertial, jitter, uniform

HOUSING_HALF = (0.03, 0.03, 0.015)
CAP_RADIUS = 0.015
CAP_HALF = 0.0125
CAP_REST = 0.0425  # cap centre above the table when released (its top at 5.5 cm, 2.5 cm above the housing)
TRAVEL = 0.024
ACTIVATION = 0.006  # press depth that activates the button
OVER_PRESS = 0.014  # press depth that counts as over-pressing
RELEASED = 0.002
#: lowest point of the closed fingers below the end-effector point (measured on the Panda hand)
FINGER_REACH = 0.0095


class PressTask(FrankaTask):
    name = "press"
    object_names = ("button",)
    id_lines = {"button": ((0.45, 0.0, HOUSING_HALF[2]), (0.55, 0.0, HOUSING_HALF[2]))}
    footprint = {"button": HOUSING_HALF[0]}
    displacements = (Displacement(("button",), (0.0, 0.15, 0.0), chunk=2),)
    max_episode_steps = 96
    subtasks = ("press the button to its activation depth",)
    info_keys = ("depth", "max_depth", "over_pressed")
    oracle_version = 2

    def mjcf(self) -> tuple[str, str]:
        hx, hy, hz = HOUSING_HALF
        cap_z = CAP_REST - hz  # cap centre relative to the housing centre
        bodies = f"""
<body name="ddp_button" pos="0.5 0 1.0">{inertial(0.5, HOUSING_HALF)}
  <geom name="ddp_button_housing" type="box" size="{hx} {hy} {hz}" rgba="0.25 0.25 0.3 1" group="3"
        friction="1 0.005 0.0001"/>
  <body name="ddp_button_cap" pos="0 0 {cap_z:.4f}">{inertial(0.02, (CAP_RADIUS, CAP_RADIUS, CAP_HALF))}
    <joint name="ddp_button_press" type="slide" axis="0 0 1" range="{-TRAVEL} 0" limited="true"
           stiffness="300" springref="0" damping="3"/>
    <geom name="ddp_button_cap_geom" type="cylinder" size="{CAP_RADIUS} {CAP_HALF}" rgba="0.85 0.15 0.15 1"
          group="3" friction="1 0.005 0.0001"/>
  </body>
</body>
<exclude body1="ddp_button" body2="ddp_button_cap"/>
"""
        return "", bodies

    def depth(self, sim) -> float:
        """How far the cap is pushed down (m); about 0.65 mm at rest, the 20 g cap sagging on its spring."""
        return -sim.joint_qpos("ddp_button_press")

    def new_state(self) -> dict:
        return {"press_max": 0.0, "max_depth": 0.0, "over_pressed": False, "pressed": False, "presses": 0}

    def update(self, sim, state: dict) -> None:
        d = self.depth(sim)
        state["max_depth"] = max(state["max_depth"], d)
        state["press_max"] = max(state["press_max"], d)
        if d > OVER_PRESS:
            state["over_pressed"] = True
        if d < RELEASED and state["press_max"] >= RELEASED:  # a press just ended
            state["presses"] += 1
            if ACTIVATION <= state["press_max"] <= OVER_PRESS and not state["over_pressed"]:
                state["pressed"] = True
            state["press_max"] = 0.0

    def success(self, sim, state: dict) -> bool:
        return bool(state["pressed"] and not state["over_pressed"])

    def failed(self, sim, state: dict) -> bool:
        return bool(state["over_pressed"])  # after a good press too: the episode fails for good

    def info(self, sim, state: dict) -> dict[str, float]:
        return {"depth": self.depth(sim), "max_depth": state.get("max_depth", 0.0),
                "over_pressed": float(state.get("over_pressed", False))}  # fmt: skip

    def oracle(self, *, id_frame: bool = False, variance: bool = True) -> WaypointOracle:
        def plan(obs, rng):
            offset = jitter(rng, [0.004, 0.004, 0.0], 3)
            hover = uniform(rng, 0.05, 0.09)
            target = uniform(rng, 0.009, 0.011)  # press depth aimed at, inside [6, 14] mm
            top = CAP_REST + CAP_HALF - HOUSING_HALF[2]  # cap top above the button's root (housing centre)
            button = lambda o: o.objects[0] + offset  # noqa: E731
            contact = FINGER_REACH + top
            yaw = uniform(rng, -0.3, 0.3)
            approach = down(yaw, *jitter(rng, [0.08, 0.08], 2))  # tilted in free space only
            leave = down(uniform(rng, -0.3, 0.3), *jitter(rng, [0.06, 0.06], 2))
            return [
                Waypoint(None, 1.0, rot=lambda o: DOWN, hold=int(uniform(rng, 2, 5)), tol=1.0, name="close"),
                Waypoint(lambda o: button(o) + [0, 0, contact + hover], 1.0, rot=lambda o: approach, tol=0.012,
                         name="above"),
                Waypoint(lambda o: button(o) + [0, 0, contact + 0.01], 1.0, rot=lambda o: down(yaw), tol=0.006,
                         name="approach"),
                Waypoint(lambda o: button(o) + [0, 0, contact - target - PRESS_LAG], 1.0, speed=0.004,
                         tol=0.0015, hold=int(uniform(rng, 2, 4)), name="press"),
                Waypoint(lambda o: button(o) + [0, 0, contact + hover], 1.0, rot=lambda o: leave, tol=0.02,
                         name="release"),
            ]

        return WaypointOracle(plan, id_frame=id_frame, variance=variance)


#: how far the commanded target has to go below the contact point for the cap to reach the
#: aimed depth (the arm's compliance against the spring; measured)
PRESS_LAG = 0.0015
