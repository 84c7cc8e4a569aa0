"""lerobot-sdp-convert-pusht: a synthetic zarr written here (always runs) and the first episodes of the
real one (skipped when absent): counts, exact values, Hub schema, next.* alignment, keypoints equal to
gym-pusht's observation, overwrite refusal and one-line errors."""

import dataclasses

import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
import gymnasium as gym
import numpy as np
import pytest
import zarr
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_sdp.pusht.convert import (
    PUSHT_TASK,
    ConversionError,
    convert_pusht,
    main,
    open_pusht_zarr,
    verify_conversion,
)

# Synthetic recording: 3 episodes of 4, 3 and 5 frames; the block sits exactly on the goal at frame 5
# (episode 1, frame 1), so only that frame has coverage 1.
LENGTHS = (4, 3, 5)
GOAL_FRAME = 5
# Hub lerobot/pusht_keypoints, episode 0 frame 0 (dataset viewer): observation.environment_state, and
# next.reward of Hub lerobot/pusht (printed to 6 digits).
HUB_KEYPOINTS_0 = [
    282.4591979980469, 373.6072692871094, 163.5284423828125, 389.5907897949219,
    159.5325469970703, 359.8581237792969, 278.46331787109375, 343.87457275390625,
    233.86427307128906, 349.868408203125, 204.131591796875, 353.8642883300781,
    192.14393615722656, 264.66619873046875, 221.87661743164062, 260.6703186035156,
]  # fmt: skip
HUB_REWARD_0 = 0.190297


def synthetic_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    n = sum(LENGTHS)
    state = np.column_stack(
        [rng.uniform(50, 450, (n, 2)), rng.uniform(120, 390, (n, 2)), rng.uniform(-np.pi, np.pi, n)]
    ).astype(np.float32)
    state[GOAL_FRAME, 2:] = (256, 256, np.pi / 4)  # gym-pusht's goal pose
    return {
        "data/state": state,
        "data/action": rng.uniform(0, 512, (n, 2)).astype(np.float32),
        # float32 holding uint8 values, as in pusht_cchi_v7_replay.zarr
        "data/img": rng.integers(0, 256, (n, 96, 96, 3)).astype(np.float32),
        "meta/episode_ends": np.cumsum(LENGTHS),
    }


def write_zarr(path, arrays):
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    for name, value in arrays.items():
        group, leaf = name.split("/")
        root.require_group(group).create_array(leaf, data=value)
    return path


def load(root, repo_id):
    """Every column of the dataset at `root`, as numpy arrays, after a LeRobotDataset reload."""
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    return dataset, dataset.hf_dataset.with_format("numpy")[:]


def env_observation(env, state):
    """gym-pusht's environment_state_agent_pos observation with agent and block where `state` has them.

    Not `reset(options={"reset_to_state": state})`: that sets the block's position before its angle, and
    pymunk rotates about the centre of gravity, so the block would land up to ~90 px from the recorded
    pose (gym-pusht's own legacy warning)."""
    unwrapped = env.unwrapped
    unwrapped.agent.position = (float(state[0]), float(state[1]))
    unwrapped.block.angle = float(state[4])
    unwrapped.block.position = (float(state[2]), float(state[3]))
    return unwrapped.get_obs()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    arrays = synthetic_arrays()
    return arrays, write_zarr(tmp_path_factory.mktemp("zarr") / "pusht.zarr", arrays)


@pytest.fixture(scope="module")
def image_dataset(synthetic, tmp_path_factory):
    out = convert_pusht(synthetic[1], tmp_path_factory.mktemp("out") / "image", variant="image")
    return load(out, "local/pusht")


@pytest.fixture
def pusht_env():
    env = gym.make("gym_pusht/PushT-v0", obs_type="environment_state_agent_pos")
    env.reset(seed=0)
    yield env
    env.close()


def test_image_variant_has_the_schema_of_hub_pusht(image_dataset):
    dataset, _ = image_dataset
    motors = {"motors": ["motor_0", "motor_1"]}
    expected = {
        "observation.image": ("image", (96, 96, 3), ["height", "width", "channel"]),
        "observation.state": ("float32", (2,), motors),
        "action": ("float32", (2,), motors),
        "next.reward": ("float32", (1,), None),
        "next.done": ("bool", (1,), None),
        "next.success": ("bool", (1,), None),
    }
    defaults = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
    features = {k: v for k, v in dataset.meta.features.items() if k not in defaults}
    assert {k: (v["dtype"], tuple(v["shape"]), v["names"]) for k, v in features.items()} == expected
    assert dataset.meta.fps == 10
    assert list(dataset.meta.tasks.index) == [PUSHT_TASK]


def test_every_frame_round_trips_exactly(synthetic, image_dataset):
    arrays, _ = synthetic
    dataset, rows = image_dataset
    assert (dataset.meta.total_episodes, dataset.meta.total_frames) == (len(LENGTHS), sum(LENGTHS))
    assert np.bincount(rows["episode_index"]).tolist() == list(LENGTHS)
    assert rows["frame_index"].tolist() == [t for n in LENGTHS for t in range(n)]
    assert np.array_equal(rows["observation.state"], arrays["data/state"][:, :2])
    assert np.array_equal(rows["action"], arrays["data/action"])
    assert np.array_equal(rows["observation.image"], arrays["data/img"].astype(np.uint8))


def test_next_labels_describe_the_frame_after_the_action(image_dataset):
    _, rows = image_dataset
    episode_1 = slice(4, 7)  # frames 4, 5 (block on the goal), 6
    assert rows["next.success"].tolist() == [i == GOAL_FRAME - 1 for i in range(sum(LENGTHS))]
    assert rows["next.reward"][GOAL_FRAME - 1] == 1.0
    # The last frame has no successor and repeats its own reward.
    assert rows["next.reward"][episode_1][1] == rows["next.reward"][episode_1][2] < 0.95
    assert np.flatnonzero(rows["next.done"]).tolist() == [3, 6, 11]


def test_keypoints_variant_is_state_only_and_equals_the_env_observation(synthetic, tmp_path, pusht_env):
    arrays, path = synthetic
    out = convert_pusht(path, tmp_path / "kp", variant="keypoints")
    dataset, rows = load(out, "local/pusht_keypoints")
    assert "observation.image" not in dataset.meta.features
    for state, keypoints, agent in zip(
        arrays["data/state"], rows["observation.environment_state"], rows["observation.state"], strict=True
    ):
        obs = env_observation(pusht_env, state)
        assert np.array_equal(keypoints, obs["environment_state"].astype(np.float32))
        assert np.array_equal(agent, obs["agent_pos"].astype(np.float32))


def test_cli_episode_subset_keeps_the_given_order(synthetic, tmp_path, capsys):
    arrays, path = synthetic
    out = tmp_path / "subset"
    main([str(path), str(out), "--variant", "keypoints", "--with-images", "--episodes", "2,0"])
    assert "--dataset.root=" in capsys.readouterr().out
    _dataset, rows = load(out, "local/pusht_keypoints")
    assert np.bincount(rows["episode_index"]).tolist() == [5, 4]
    zarr_frames = np.r_[7:12, 0:4]  # zarr episode 2, then episode 0
    assert np.array_equal(rows["action"], arrays["data/action"][zarr_frames])
    assert np.array_equal(rows["observation.image"], arrays["data/img"][zarr_frames].astype(np.uint8))


def test_refuses_to_overwrite_without_the_flag(synthetic, tmp_path):
    _, path = synthetic
    out = convert_pusht(path, tmp_path / "ds", variant="keypoints", episodes=[0], verify=False)
    with pytest.raises(ConversionError, match="already exists; pass --overwrite"):
        convert_pusht(path, out, variant="keypoints", episodes=[1])
    assert load(out, "local/pusht_keypoints")[0].meta.total_frames == LENGTHS[0]
    convert_pusht(path, out, variant="keypoints", episodes=[1], overwrite=True)
    assert load(out, "local/pusht_keypoints")[0].meta.total_frames == LENGTHS[1]
    # --overwrite deletes only what the converter could have written.
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(ConversionError, match="not a LeRobot dataset"):
        convert_pusht(path, precious, overwrite=True)
    assert (precious / "notes.txt").exists()


def _drop(name):
    return lambda arrays: {k: v for k, v in arrays.items() if k != name}


def _set(name, value_of):
    return lambda arrays: {**arrays, name: value_of(arrays[name])}


@pytest.mark.parametrize(
    "corrupt, args, message",
    [
        (None, [], "does not exist; pass the path of pusht_cchi_v7_replay.zarr"),
        (lambda arrays: {}, [], "is not a zarr group"),
        (_drop("data/action"), [], "lacks data/action"),
        (_set("data/action", lambda a: a[:-1]), [], "data/action has shape (11, 2), expected (12, 2)"),
        (_set("meta/episode_ends", lambda e: e - 1), [], "ends at frame 11 but data/state has 12 frames"),
        (_set("meta/episode_ends", lambda e: e[[1, 0, 2]]), [], "is not strictly increasing"),
        (_set("data/img", lambda img: img + 0.5), [], "not integers in 0..255"),
        (lambda arrays: arrays, ["--episodes", "0,9"], "[9] do not exist; the zarr has episodes 0..2"),
        (lambda arrays: arrays, ["--episodes", "1,1"], "repeat an episode"),
        (lambda arrays: arrays, ["--episodes", "one"], "is not START:STOP or a comma list"),
    ],
    ids=[
        "missing-path", "not-a-zarr", "missing-array", "short-array", "episode-ends-short",
        "episode-ends-unordered", "lossy-images", "episode-out-of-range", "episode-repeated",
        "bad-episode-spec",
    ],
)  # fmt: skip
def test_bad_input_is_one_clear_line_and_leaves_nothing(corrupt, args, message, tmp_path, capsys):
    path = tmp_path / "pusht.zarr"
    if corrupt is not None:
        arrays = corrupt(synthetic_arrays())
        if arrays:
            write_zarr(path, arrays)
        else:
            path.mkdir()  # a directory, but no zarr
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_info:
        main([str(path), str(out), *args])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("lerobot-sdp-convert-pusht: error: ")
    assert message in err
    assert not out.exists()


def test_verification_catches_a_changed_value(synthetic, image_dataset):
    _, path = synthetic
    dataset, _ = image_dataset
    data = open_pusht_zarr(path, with_images=True)
    verify_conversion(data, dataset.root, "local/pusht", "image", [0, 1, 2], True)
    nudged = dataclasses.replace(data, action=data.action + np.float32(1e-3))
    with pytest.raises(ConversionError, match="action of episode 0"):
        verify_conversion(nudged, dataset.root, "local/pusht", "image", [0, 1, 2], True)


def test_real_first_episodes_round_trip_and_match_the_hub(pusht_zarr, tmp_path):
    out = convert_pusht(pusht_zarr, tmp_path / "real", variant="keypoints", episodes="0:3", with_images=True)
    dataset, rows = load(out, "local/pusht_keypoints")
    source = zarr.open_group(str(pusht_zarr), mode="r")
    n = int(source["meta/episode_ends"][2])
    assert (dataset.meta.total_episodes, dataset.meta.total_frames, n) == (3, 420, 420)
    assert np.bincount(rows["episode_index"]).tolist() == [161, 118, 141]
    assert np.array_equal(rows["observation.state"], source["data/state"][:n, :2])
    assert np.array_equal(rows["action"], source["data/action"][:n])
    assert np.array_equal(rows["observation.image"], source["data/img"][:n].astype(np.uint8))
    assert np.array_equal(rows["observation.environment_state"][0], np.float32(HUB_KEYPOINTS_0))
    assert abs(rows["next.reward"][0] - HUB_REWARD_0) < 5e-7


def rigid_transform(src, dst):
    """Least-squares rotation R and translation t with dst ≈ src @ R.T + t (Kabsch)."""
    src_mean, dst_mean = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - src_mean).T @ (dst - dst_mean))
    rotation = vt.T @ np.diag([1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return rotation, dst_mean - src_mean @ rotation.T


def test_real_keypoints_equal_the_env_observation_and_the_recorded_block(pusht_zarr, tmp_path, pusht_env):
    out = convert_pusht(pusht_zarr, tmp_path / "real", variant="keypoints", episodes="0:2")
    _, rows = load(out, "local/pusht_keypoints")
    n = len(rows["index"])
    source = zarr.open_group(str(pusht_zarr), mode="r")
    state, recorded = source["data/state"][:n], source["data/keypoint"][:n].astype(np.float64)
    ours = rows["observation.environment_state"].astype(np.float64).reshape(n, 8, 2)
    for t in range(n):
        obs = env_observation(pusht_env, state[t])
        assert np.array_equal(ours[t], obs["environment_state"].astype(np.float32).reshape(8, 2))
        # The zarr's own 9 keypoints (Diffusion Policy's, recorded from the live block) move rigidly with
        # ours: the converted pose is the block's pose at recording time.
        rotation, shift = rigid_transform(ours[0], ours[t])
        assert np.abs(recorded[0] @ rotation.T + shift - recorded[t]).max() < 0.5
