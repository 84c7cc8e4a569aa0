"""The scripted demonstrators: the phase machines on hand-made observations (no robosuite), and a
full Can episode in robosuite that ends with the can in its compartment and the gripper clear."""

from types import SimpleNamespace

import numpy as np
import pytest

from lerobot_sdp.robomimic.demonstrators import CLOSED, OPEN, CanDemonstrator, LiftDemonstrator

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


def test_a_can_episode_ends_with_the_can_placed_and_the_gripper_clear():
    pytest.importorskip(
        "robosuite", reason="robosuite is not installed: pip install 'lerobot_policy_sdp[robomimic]'"
    )
    from lerobot_sdp.robomimic.env import RobomimicEnv

    env = RobomimicEnv("PickPlaceCan")
    d = CanDemonstrator(np.random.default_rng(1))
    env.reset(seed=100_001)
    d.reset(env.sim_env)
    phases = []
    for _ in range(400):
        _, reward, terminated, truncated, info = env.step(d.act(env.raw_observation))
        if not phases or phases[-1] != d.phase:
            phases.append(d.phase)
        if terminated or truncated:
            break
    raw = env.raw_observation
    env.close()
    assert terminated and info["is_success"] and reward == 1.0
    assert phases[-1] == "retreat" and {"carry", "lower", "release"} <= set(phases)
    # In the can's quarter of the right-hand bin, resting on its floor, the gripper more than 4 cm away.
    assert np.abs(raw["Can_pos"][:2] - COMPARTMENT[:2]).max() < 0.06
    assert raw["Can_pos"][2] < COMPARTMENT[2] + 0.1
    assert np.linalg.norm(raw["robot0_eef_pos"] - raw["Can_pos"]) > 0.04
