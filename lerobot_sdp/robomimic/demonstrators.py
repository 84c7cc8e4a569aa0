"""Scripted demonstrators for robomimic's Lift and Can, standing in for robomimic's human demonstrations.

No robomimic dataset is reachable from our machines. Both demonstrators are phase machines over
robosuite's raw observations that steer the end effector with proportional OSC_POSE position deltas
(no rotation: the gripper keeps its start orientation, fingers straddling the object from above):

- Lift: reach above the cube, descend, close the gripper, lift.
- Can (`PickPlaceCan`): the same grasp on the can, then lift over the bin walls, carry to above the
  can's compartment of the target bin, lower, open, and rise until the gripper is clear (the task
  counts a success only with the can in its compartment and the gripper more than 4 cm away).

If the object slips out of the fingers while held, the demonstrator opens and starts over from the
reach. Each episode draws its own style (gain, heights, grasp offset, grasp duration, placement
offset, action-noise level), so demonstrations vary the way human ones do.
"""

from dataclasses import dataclass

import numpy as np

# OSC_POSE maps an action of 1 to a 5 cm goal displacement (robosuite's output_max).
METERS_PER_ACTION = 0.05
OPEN, CLOSED = -1.0, 1.0
# Farther than this from the end effector, a held object has slipped out of the fingers (m).
SLIPPED = 0.04


@dataclass
class GraspStyle:
    """One episode's randomised parameters of the approach and grasp, shared by both tasks."""

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
    """Reach -> descend -> grasp over one object, then the task's own phases (`_carry`).

    `act(raw_obs)` turns robosuite's raw observation dict into a 7-d OSC_POSE action. Subclasses name
    the object's observation key and draw their style in `_draw_style`.
    """

    object_key: str

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def reset(self, sim_env) -> None:
        """Start an episode in robosuite env `sim_env` (just reset) with a fresh style."""
        self.style = self._draw_style()
        self.phase, self.phase_steps = "reach", 0
        self.start: np.ndarray | None = None  # the object's position at the first step

    def _draw_style(self) -> GraspStyle:
        raise NotImplementedError

    def act(self, obs: dict) -> np.ndarray:
        eef, obj = obs["robot0_eef_pos"], obs[self.object_key]
        if self.start is None:
            self.start = obj.copy()
        target, gripper = self._target(eef, obj)
        self.phase_steps += 1
        move = self.style.gain * (target - eef) / METERS_PER_ACTION + self.rng.normal(0, self.style.noise, 3)
        return np.concatenate([np.clip(move, -1, 1), np.zeros(3), [gripper]])

    def _goto(self, phase: str) -> None:
        self.phase, self.phase_steps = phase, 0

    def _target(self, eef: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, float]:
        grasp_point = obj + self.style.offset
        above = grasp_point + np.array([0, 0, self.style.hover])
        if self.phase == "reach":
            if np.linalg.norm((above - eef)[:2]) < 0.01 and abs(above[2] - eef[2]) < 0.02:
                self._goto("descend")
            return above, OPEN
        if self.phase == "descend":
            if np.linalg.norm(grasp_point - eef) < 0.008 or self.phase_steps > 60:
                self._goto("grasp")
            return grasp_point, OPEN
        if self.phase == "grasp":
            if self.phase_steps >= self.style.grasp_steps:
                self._goto("lift")
            return grasp_point, CLOSED
        if self._holding() and np.linalg.norm(obj - eef) > SLIPPED:
            self._goto("reach")  # the object slipped: open and start over
            return eef, OPEN
        return self._carry(eef)

    def _holding(self) -> bool:
        """Whether the current phase expects the object between the fingers."""
        return True

    def _carry(self, eef: np.ndarray) -> tuple[np.ndarray, float]:
        """Target and gripper command of the phases after the grasp."""
        raise NotImplementedError


@dataclass
class LiftStyle(GraspStyle):
    lift: float  # lift height above the cube's start (m)


class LiftDemonstrator(GraspDemonstrator):
    """Lift the cube (robosuite's `cube_pos`) straight up."""

    object_key = "cube_pos"

    def _draw_style(self) -> LiftStyle:
        return LiftStyle(**GraspStyle.draw(self.rng, (-0.012, 0.0)), lift=self.rng.uniform(0.10, 0.20))

    def _carry(self, eef: np.ndarray) -> tuple[np.ndarray, float]:
        return np.array([eef[0], eef[1], self.start[2] + self.style.lift]), CLOSED


@dataclass
class CanStyle(GraspStyle):
    carry: float  # carrying height (m, world z; the bins' walls end near 0.9)
    place: np.ndarray  # offset of the release point from the compartment's centre (m, x and y)
    release: float  # height of the grasp point above the bin floor at release (m)
    open_steps: int  # steps the gripper opens before rising


class CanDemonstrator(GraspDemonstrator):
    """Pick the can (robosuite's `Can_pos`) from the left bin and place it in its compartment."""

    object_key = "Can_pos"

    def reset(self, sim_env) -> None:
        super().reset(sim_env)
        # robosuite's own target: the centre of the can's quarter of the right-hand bin, at its floor.
        self.compartment = np.array(sim_env.target_bin_placements[sim_env.object_id])

    def _draw_style(self) -> CanStyle:
        rng = self.rng
        return CanStyle(
            **GraspStyle.draw(rng, (-0.01, 0.01)),
            carry=rng.uniform(1.0, 1.06),
            place=rng.uniform(-0.03, 0.03, 2),
            release=rng.uniform(0.09, 0.12),
            open_steps=int(rng.integers(4, 9)),
        )

    def _holding(self) -> bool:
        return self.phase in ("lift", "carry", "lower")

    def _carry(self, eef: np.ndarray) -> tuple[np.ndarray, float]:
        style = self.style
        place = self.compartment[:2] + style.place
        if self.phase == "lift":
            if eef[2] > style.carry - 0.02:
                self._goto("carry")
            return np.array([eef[0], eef[1], style.carry]), CLOSED
        if self.phase == "carry":
            if np.linalg.norm(place - eef[:2]) < 0.01:
                self._goto("lower")
            return np.array([*place, style.carry]), CLOSED
        if self.phase == "lower":
            release_z = self.compartment[2] + style.release
            if eef[2] < release_z + 0.01 or self.phase_steps > 40:
                self._goto("release")
            return np.array([*place, release_z]), CLOSED
        if self.phase == "release":
            if self.phase_steps >= style.open_steps:
                self._goto("retreat")
            return eef, OPEN
        return np.array([eef[0], eef[1], style.carry]), OPEN  # retreat: rise clear of the can


DEMONSTRATORS: dict[str, type[GraspDemonstrator]] = {
    "Lift": LiftDemonstrator,
    "PickPlaceCan": CanDemonstrator,
}
