"""Scripted demonstrators for robomimic's Lift, Can and Square, standing in for robomimic's human
demonstrations (no robomimic dataset is reachable from our machines).

All three are phase machines over robosuite's observations that steer the end effector with
proportional OSC_POSE deltas (robosuite maps an action of 1 to 5 cm or 0.5 rad):

- Lift: reach above the cube, descend, close the gripper, lift.
- Can (`PickPlaceCan`): the same grasp on the can, then lift over the bin walls, carry to above the
  can's compartment of the target bin, lower, open, and rise until the gripper is clear (the task
  counts a success only with the can in its compartment and the gripper more than 4 cm away).
- Square (`NutAssemblySquare`): turn the fingers across the nut's handle while reaching it, grasp
  the handle, lift, carry the nut over the square peg while turning it square to the peg, lower it
  onto the peg (success: the nut around the peg, near the table), open and rise.

Lift and Can keep the gripper's start orientation (fingers straddle the object from above); only
Square turns it, about the vertical. If the object slips out of the fingers while held, the
demonstrator opens and starts over from the reach. Each episode draws its own style (gain, heights,
grasp offset, grasp duration, placement offset, action-noise level), so demonstrations vary the way
human ones do. Scripted demonstrators may read the simulator beyond the policy's observations (the
can's target compartment, the nut's handle, the peg): they stand in for a human who sees the scene.
"""

from dataclasses import dataclass

import numpy as np

# OSC_POSE maps an action of 1 to a 5 cm goal displacement and a 0.5 rad turn (robosuite's output_max).
METERS_PER_ACTION = 0.05
RADIANS_PER_ACTION = 0.5
OPEN, CLOSED = -1.0, 1.0
# Farther than this from the end effector, a held object has slipped out of the fingers (m).
SLIPPED = 0.04


def wrap(angle: float, period: float) -> float:
    """`angle` to the equivalent one in [-period / 2, period / 2)."""
    return (angle + period / 2) % period - period / 2


def yaw(quat_xyzw: np.ndarray) -> float:
    """Rotation about the vertical of a quaternion (x, y, z, w), robosuite's order."""
    x, y, z, w = quat_xyzw
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


@dataclass
class GraspStyle:
    """One episode's randomised parameters of the approach and grasp, shared by all tasks."""

    gain: float  # fraction of the remaining distance commanded per step
    hover: float  # height above the grasp point before descending (m)
    offset: np.ndarray  # grasp point offset from the object's centre (m)
    grasp_steps: int  # steps the gripper closes before lifting
    noise: float  # std of the Gaussian noise on position actions

    @staticmethod
    def draw(rng: np.random.Generator, z_offset: tuple[float, float]) -> dict:
        return dict(
            gain=rng.uniform(0.5, 1.0),
            hover=rng.uniform(0.05, 0.12),
            offset=np.array([*rng.uniform(-0.006, 0.006, 2), rng.uniform(*z_offset)]),
            grasp_steps=int(rng.integers(6, 14)),
            noise=rng.uniform(0.0, 0.1),
        )


class GraspDemonstrator:
    """Reach -> descend -> grasp, then the task's own phases (`_after_grasp`).

    `act(raw_obs)` turns robosuite's raw observation dict into a 7-d OSC_POSE action. Subclasses name
    the object's observation key, draw their style and may move the grasp point or turn the gripper.
    """

    object_key: str

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def reset(self, sim_env) -> None:
        """Start an episode in robosuite env `sim_env` (just reset) with a fresh style."""
        self.sim_env = sim_env
        self.style = self._draw_style()
        self.phase, self.phase_steps = "reach", 0
        self.start: np.ndarray | None = None  # the object's position at the first step

    def _draw_style(self) -> GraspStyle:
        raise NotImplementedError

    def act(self, obs: dict) -> np.ndarray:
        eef = obs["robot0_eef_pos"]
        if self.start is None:
            self.start = obs[self.object_key].copy()
        target, turn, gripper = self._target(eef, obs)
        self.phase_steps += 1
        move = self.style.gain * (target - eef) / METERS_PER_ACTION + self.rng.normal(0, self.style.noise, 3)
        rotate = [0.0, 0.0, self.style.gain * turn / RADIANS_PER_ACTION]
        return np.concatenate([np.clip(move, -1, 1), np.clip(rotate, -1, 1), [gripper]])

    def _goto(self, phase: str) -> None:
        self.phase, self.phase_steps = phase, 0

    def _grasp_point(self, obs: dict) -> np.ndarray:
        """Where the fingers close."""
        return obs[self.object_key] + self.style.offset

    def _grasp_turn(self, obs: dict) -> float:
        """Turn about the vertical (rad) that puts the fingers across the grasp; 0 keeps the start one."""
        return 0.0

    def _target(self, eef: np.ndarray, obs: dict) -> tuple[np.ndarray, float, float]:
        """(position target, turn about the vertical, gripper command) of the current phase."""
        grasp_point = self._grasp_point(obs)
        above = grasp_point + np.array([0, 0, self.style.hover])
        if self.phase == "reach":
            turn = self._grasp_turn(obs)
            lined_up = np.linalg.norm((above - eef)[:2]) < 0.01 and abs(above[2] - eef[2]) < 0.02
            if lined_up and abs(turn) < 0.05:
                self._goto("descend")
            return above, turn, OPEN
        if self.phase == "descend":
            if np.linalg.norm(grasp_point - eef) < 0.008 or self.phase_steps > 60:
                self._goto("grasp")
            return grasp_point, self._grasp_turn(obs), OPEN
        if self.phase == "grasp":
            if self.phase_steps >= self.style.grasp_steps:
                self._goto("lift")
            return grasp_point, 0.0, CLOSED
        if self._holding() and np.linalg.norm(grasp_point - eef) > SLIPPED:
            self._goto("reach")  # the object slipped: open and start over
            return eef, 0.0, OPEN
        return self._after_grasp(eef, obs)

    def _holding(self) -> bool:
        """Whether the current phase expects the object between the fingers."""
        return True

    def _after_grasp(self, eef: np.ndarray, obs: dict) -> tuple[np.ndarray, float, float]:
        raise NotImplementedError


@dataclass
class LiftStyle(GraspStyle):
    lift: float  # lift height above the cube's start (m)


class LiftDemonstrator(GraspDemonstrator):
    """Lift the cube (robosuite's `cube_pos`) straight up."""

    object_key = "cube_pos"

    def _draw_style(self) -> LiftStyle:
        return LiftStyle(**GraspStyle.draw(self.rng, (-0.012, 0.0)), lift=self.rng.uniform(0.10, 0.20))

    def _after_grasp(self, eef: np.ndarray, obs: dict) -> tuple[np.ndarray, float, float]:
        return np.array([eef[0], eef[1], self.start[2] + self.style.lift]), 0.0, CLOSED


@dataclass
class PlaceStyle(GraspStyle):
    carry: float  # carrying height (m, world z)
    place: np.ndarray  # offset of the release point from the place's centre (m, x and y)
    release: float  # height of the end effector above the place's floor at release (m)
    open_steps: int  # steps the gripper opens before rising

    @staticmethod
    def draw_place(rng: np.random.Generator, place: float, release: tuple[float, float]) -> dict:
        return dict(
            carry=rng.uniform(1.0, 1.06),
            place=rng.uniform(-place, place, 2),
            release=rng.uniform(*release),
            open_steps=int(rng.integers(4, 9)),
        )


class PlaceDemonstrator(GraspDemonstrator):
    """After the grasp: lift to the carrying height, carry over the place, lower, open, rise."""

    def _holding(self) -> bool:
        return self.phase in ("lift", "carry", "lower")

    def _place(self, eef: np.ndarray, obs: dict) -> np.ndarray:
        """The end effector's (x, y) over the place, the floor's z: where the object is let go."""
        raise NotImplementedError

    def _placing_turn(self, obs: dict) -> float:
        """Turn about the vertical (rad) the held object needs to fit the place."""
        return 0.0

    def _after_grasp(self, eef: np.ndarray, obs: dict) -> tuple[np.ndarray, float, float]:
        style = self.style
        x, y, floor = self._place(eef, obs)
        if self.phase == "lift":
            if eef[2] > style.carry - 0.02:
                self._goto("carry")
            return np.array([eef[0], eef[1], style.carry]), 0.0, CLOSED
        if self.phase == "carry":
            turn = self._placing_turn(obs)
            if np.linalg.norm([x - eef[0], y - eef[1]]) < 0.01 and abs(turn) < 0.03:
                self._goto("lower")
            return np.array([x, y, style.carry]), turn, CLOSED
        if self.phase == "lower":
            release_z = floor + style.release
            if eef[2] < release_z + 0.01 or self.phase_steps > 60:
                self._goto("release")
            return np.array([x, y, release_z]), self._placing_turn(obs), CLOSED
        if self.phase == "release":
            if self.phase_steps >= style.open_steps:
                self._goto("retreat")
            return eef, 0.0, OPEN
        return np.array([eef[0], eef[1], style.carry]), 0.0, OPEN  # retreat: rise clear of the object


class CanDemonstrator(PlaceDemonstrator):
    """Pick the can (robosuite's `Can_pos`) from the left bin and place it in its compartment."""

    object_key = "Can_pos"

    def reset(self, sim_env) -> None:
        super().reset(sim_env)
        # robosuite's own target: the centre of the can's quarter of the right-hand bin, at its floor.
        self.compartment = np.array(sim_env.target_bin_placements[sim_env.object_id])

    def _draw_style(self) -> PlaceStyle:
        grasp = GraspStyle.draw(self.rng, (-0.01, 0.01))
        return PlaceStyle(**grasp, **PlaceStyle.draw_place(self.rng, 0.03, (0.09, 0.12)))

    def _place(self, eef: np.ndarray, obs: dict) -> np.ndarray:
        return np.array([*(self.compartment[:2] + self.style.place), self.compartment[2]])


class SquareDemonstrator(PlaceDemonstrator):
    """Pick the square nut by its handle and fit it onto the square peg."""

    object_key = "SquareNut_pos"

    def reset(self, sim_env) -> None:
        super().reset(sim_env)
        self.peg = np.array(sim_env.sim.data.body_xpos[sim_env.peg1_body_id])  # peg1 is the square one

    def _draw_style(self) -> PlaceStyle:
        grasp = GraspStyle.draw(self.rng, (-0.005, 0.005))
        grasp |= {"hover": self.rng.uniform(0.05, 0.10), "noise": self.rng.uniform(0.0, 0.05)}
        # The nut must go round the peg: no placement offset; it is let go just above the table (the
        # task counts it placed below 5 cm).
        return PlaceStyle(**grasp, **PlaceStyle.draw_place(self.rng, 0.0, (0.0, 0.03)))

    def _grasp_point(self, obs: dict) -> np.ndarray:
        sim = self.sim_env
        handle = sim.sim.data.site_xpos[sim.object_site_ids[sim.nut_id]]
        return np.array(handle) + self.style.offset

    def _finger_yaw(self) -> float:
        """Direction of the gripper's x axis about the vertical; the handle must lie along it."""
        sim = self.sim_env
        axes = sim.sim.data.site_xmat[sim.robots[0].eef_site_id["right"]].reshape(3, 3)
        return float(np.arctan2(axes[1, 0], axes[0, 0]))

    def _grasp_turn(self, obs: dict) -> float:
        # The handle sticks out along the nut's x axis; the fingers close across it. A gripper is the
        # same turned by half a turn, so the smaller of the two turns is taken.
        return wrap(yaw(obs["SquareNut_quat"]) + np.pi / 2 - self._finger_yaw(), np.pi)

    def _placing_turn(self, obs: dict) -> float:
        return wrap(-yaw(obs["SquareNut_quat"]), np.pi / 2)  # a square fits every quarter turn

    def _place(self, eef: np.ndarray, obs: dict) -> np.ndarray:
        # The end effector holds the handle: the nut's centre, not the hand, goes over the peg and
        # down to the table.
        hand_from_nut = eef - obs[self.object_key]
        return np.array(
            [*(self.peg[:2] + hand_from_nut[:2]), self.sim_env.table_offset[2] + hand_from_nut[2]]
        )


DEMONSTRATORS: dict[str, type[GraspDemonstrator]] = {
    "Lift": LiftDemonstrator,
    "PickPlaceCan": CanDemonstrator,
    "NutAssemblySquare": SquareDemonstrator,
}
