"""The scripted demonstrators: the phase machines on hand-made observations (no robosuite), and full
Can and Square episodes in robosuite that end with the object placed and the gripper clear."""

from types import SimpleNamespace

import numpy as np
import pytest

from lerobot_sdp.robomimic.demonstrators import (
    CLOSED,
    OPEN,
    CanDemonstrator,
    LiftDemonstrator,
    SquareDemonstrator,
    wrap,
    yaw,
)

# A stand-in for robosuite's PickPlaceCan: the can's compartment is placement 3 (robosuite's layout).
COMPARTMENT = np.array([0.1975, 0.4025, 0.8])
SIM = SimpleNamespace(target_bin_placements=np.array([[0, 0, 0]] * 3 + [COMPARTMENT]), object_id=3)


def can_demonstrator(seed: int = 0) -> CanDemonstrator:
    d = CanDemonstrator(np.random.default_rng(seed))
    d.reset(SIM)
    d.style.noise = 0.0  # exact commands
    return d


def obs(eef, can) -> dict:
    return {"robot0_eef_pos": np.asarray(eef, float), "Can_pos": np.asarray(can, float)}


def test_styles_vary_per_episode_and_repeat_per_seed():
    a, b = can_demonstrator(0), can_demonstrator(0)
    assert a.style.carry == b.style.carry and np.array_equal(a.style.place, b.style.place)
    a.reset(SIM)
    assert a.style.carry != b.style.carry  # the next episode draws a new style


def test_can_phases_steer_to_the_can_then_to_its_compartment():
    d = can_demonstrator()
    can = np.array([0.05, -0.2, 0.86])
    grasp_point = can + d.style.offset
    action = d.act(obs(grasp_point + np.array([0, 0, 0.3]), can))  # high above: move down, gripper open
    assert d.phase == "reach" and action[2] < 0 and action[6] == OPEN
    assert np.array_equal(action[3:6], np.zeros(3))  # never rotates
    d.act(obs(grasp_point + np.array([0, 0, d.style.hover]), can))
    assert d.phase == "descend"
    d.act(obs(grasp_point, can))
    assert d.phase == "grasp"
    for _ in range(d.style.grasp_steps):
        action = d.act(obs(grasp_point, can))
    assert d.phase == "lift" and action[6] == CLOSED
    held = np.array([*grasp_point[:2], d.style.carry])  # lifted to the carrying height, can in hand
    action = d.act(obs(held, held - d.style.offset))
    assert d.phase == "carry"
    action = d.act(obs(held, held - d.style.offset))
    # Towards the compartment: +y from the left bin to the right one, gripper closed.
    assert action[1] > 0 and action[6] == CLOSED
    place = np.array([*(COMPARTMENT[:2] + d.style.place), d.style.carry])
    d.act(obs(place, place - d.style.offset))
    assert d.phase == "lower"
    low = np.array([*place[:2], COMPARTMENT[2] + d.style.release])
    d.act(obs(low, low - d.style.offset))
    assert d.phase == "release"
    for _ in range(d.style.open_steps):
        assert d.phase == "release"  # opens in place for open_steps steps
        action = d.act(obs(low, low - d.style.offset))
        assert action[6] == OPEN and np.abs(action[:3]).max() == 0.0
    assert d.phase == "retreat"
    action = d.act(obs(low, low - d.style.offset))
    assert action[2] > 0 and action[6] == OPEN  # rises clear, gripper open


def test_a_can_that_slips_while_carried_is_picked_up_again():
    d = can_demonstrator()
    d.phase = "carry"
    eef = np.array([0.1, 0.0, 1.0])
    action = d.act(obs(eef, eef - [0, 0, 0.14]))  # the can fell out of the fingers
    assert d.phase == "reach" and action[6] == OPEN
    d.phase = "retreat"  # after the release the can is meant to be left behind
    d.act(obs(eef, eef - [0, 0, 0.14]))
    assert d.phase == "retreat"


def test_lift_rises_above_the_cube_start_and_regrasps_a_dropped_cube():
    d = LiftDemonstrator(np.random.default_rng(0))
    d.reset(None)
    d.style.noise = 0.0
    cube = np.array([0.0, 0.0, 0.82])
    grasped = {"robot0_eef_pos": cube + d.style.offset, "cube_pos": cube}
    d.act(grasped)  # the first observation fixes the cube's start height
    d.phase = "lift"
    action = d.act(grasped)
    assert action[2] > 0 and action[6] == CLOSED
    d.act({"robot0_eef_pos": cube + np.array([0, 0, 0.1]), "cube_pos": cube})  # the cube stayed on the table
    assert d.phase == "reach"


def about_z(angle: float) -> np.ndarray:
    """The quaternion (x, y, z, w) of a turn about the vertical."""
    return np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)])


def test_yaw_and_wrap():
    for angle in (-3.0, -1.2, 0.0, 0.4, 3.1):
        assert yaw(about_z(angle)) == pytest.approx(angle)
    assert wrap(np.radians(-80), np.pi / 2) == pytest.approx(np.radians(10))  # a square: a quarter turn
    assert wrap(np.radians(100), np.pi) == pytest.approx(np.radians(-80))  # the gripper: half a turn


def test_square_turns_the_nut_the_short_way_to_the_peg():
    d = SquareDemonstrator(np.random.default_rng(0))
    for nut_yaw, turn in ((80, 10), (10, -10), (-50, -40), (135, -45)):
        got = np.degrees(d._placing_turn({"SquareNut_quat": about_z(np.radians(nut_yaw))}))
        assert got == pytest.approx(turn) or (abs(turn) == 45 and got == pytest.approx(-turn))


@pytest.fixture(scope="module")
def robosuite_env():
    pytest.importorskip(
        "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
    )
    from lerobot_sdp.robomimic.env import RobomimicEnv

    return RobomimicEnv


def run_episode(env, demonstrator, seed: int) -> tuple[bool, list[str], dict]:
    """One scripted episode; (success, the phases in order, the last raw observation)."""
    env.reset(seed=seed)
    demonstrator.reset(env.sim_env)
    phases, success = [], False
    for _ in range(400):
        _, reward, success, truncated, info = env.step(demonstrator.act(env.raw_observation))
        if not phases or phases[-1] != demonstrator.phase:
            phases.append(demonstrator.phase)
        if success or truncated:
            break
    assert success == info["is_success"] and reward == float(success)
    return success, phases, env.raw_observation


def test_a_can_episode_ends_with_the_can_placed_and_the_gripper_clear(robosuite_env):
    env = robosuite_env("PickPlaceCan")
    success, phases, raw = run_episode(env, CanDemonstrator(np.random.default_rng(1)), 100_001)
    env.close()
    assert success and phases[-1] == "retreat" and {"carry", "lower", "release"} <= set(phases)
    # In the can's quarter of the right-hand bin, resting on its floor, the gripper more than 4 cm away.
    assert np.abs(raw["Can_pos"][:2] - COMPARTMENT[:2]).max() < 0.06
    assert raw["Can_pos"][2] < COMPARTMENT[2] + 0.1
    assert np.linalg.norm(raw["robot0_eef_pos"] - raw["Can_pos"]) > 0.04


def test_a_square_episode_ends_with_the_nut_around_the_peg(robosuite_env):
    env = robosuite_env("NutAssemblySquare")
    # A scene where fingers closing along the handle, instead of across it, lose the nut.
    demonstrator = SquareDemonstrator(np.random.default_rng(100_000))
    success, phases, raw = run_episode(env, demonstrator, 100_000)
    table_z = env.sim_env.table_offset[2]
    env.close()
    assert success and {"carry", "lower"} <= set(phases)
    assert np.abs(raw["SquareNut_pos"][:2] - demonstrator.peg[:2]).max() < 0.03
    assert raw["SquareNut_pos"][2] < table_z + 0.05
    # Square to the peg (a quarter turn is the same square).
    assert abs(wrap(yaw(raw["SquareNut_quat"]), np.pi / 2)) < 0.1
