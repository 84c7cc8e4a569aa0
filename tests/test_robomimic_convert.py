"""The robomimic hdf5 -> LeRobotDataset converter, on small files the tests write (h5py, no robosuite)."""

import json

import numpy as np
import pytest

h5py = pytest.importorskip(
    "h5py", reason="the converter needs h5py: pip install 'lerobot_policy_sdp[robomimic]'"
)

from lerobot_sdp.robomimic.convert import convert, main  # noqa: E402 (after the importorskip)
from lerobot_sdp.robomimic.tasks import get_task  # noqa: E402

LENGTHS = {"demo_0": 5, "demo_1": 7, "demo_10": 4}  # demo_10 after demo_1: numeric order
IMAGE = 8


def write_robomimic(path, task="Lift", lengths=LENGTHS, images=True, env_args=True):
    """A robomimic-layout file with random observations of the task's real shapes."""
    spec = get_task(task)
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        if env_args:
            data.attrs["env_args"] = json.dumps(
                {"env_name": task, "type": 1, "env_kwargs": {"control_freq": 20}}
            )
        for name, length in lengths.items():
            demo = data.create_group(name)
            demo.attrs["num_samples"] = length
            for arm in range(spec.n_arms):
                demo[f"obs/robot{arm}_eef_pos"] = rng.normal(size=(length, 3))
                demo[f"obs/robot{arm}_eef_quat"] = rng.normal(size=(length, 4))
                demo[f"obs/robot{arm}_gripper_qpos"] = rng.normal(size=(length, 2))
            demo["obs/object"] = rng.normal(size=(length, spec.object_dim))
            if images:
                for cam in spec.cameras:
                    demo[f"obs/{cam}_image"] = rng.integers(0, 256, (length, IMAGE, IMAGE, 3), dtype=np.uint8)
            demo["actions"] = rng.uniform(-1, 1, (length, spec.action_dim))
            demo["rewards"] = np.eye(length)[-1]
            demo["dones"] = np.eye(length, dtype=np.int64)[-1]
        f["mask/train"] = np.array([b"demo_1", b"demo_10"])
    return path


@pytest.fixture
def lift_hdf5(tmp_path):
    return write_robomimic(tmp_path / "lift.hdf5")


def test_low_dim_conversion_keeps_everything(lift_hdf5, tmp_path):
    dataset = convert(lift_hdf5, tmp_path / "ds", "local/lift")
    assert dataset.meta.total_episodes == 3
    assert dataset.meta.total_frames == sum(LENGTHS.values())
    assert dataset.fps == 20
    assert dataset.features["observation.state"]["shape"] == (9,)
    assert dataset.features["observation.environment_state"]["shape"] == (10,)
    assert dataset.features["action"]["shape"] == (7,)
    assert not any(key.startswith("observation.images") for key in dataset.features)
    # Episode 1 is demo_1 (numeric order), its first state is the source's first state.
    with h5py.File(lift_hdf5) as f:
        first = np.concatenate(
            [f[f"data/demo_1/obs/robot0_{k}"][0] for k in ("eef_pos", "eef_quat", "gripper_qpos")]
        )
    item = dataset[LENGTHS["demo_0"]]
    assert item["episode_index"].item() == 1
    np.testing.assert_allclose(item["observation.state"].numpy(), first.astype(np.float32))
    assert dataset.meta.tasks.index.tolist() == ["lift the cube"]


def test_image_conversion_keeps_images(lift_hdf5, tmp_path):
    dataset = convert(lift_hdf5, tmp_path / "ds", "local/lift", obs_type="image")
    assert dataset.features["observation.images.agentview"]["shape"] == (IMAGE, IMAGE, 3)
    assert "observation.environment_state" not in dataset.features
    with h5py.File(lift_hdf5) as f:
        want = f["data/demo_0/obs/robot0_eye_in_hand_image"][2]
    got = dataset[2]["observation.images.robot0_eye_in_hand"]  # float CHW in [0, 1]
    np.testing.assert_array_equal((got.numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8), want)


def test_transport_has_both_arms(tmp_path):
    path = write_robomimic(tmp_path / "transport.hdf5", task="TwoArmTransport", images=False)
    dataset = convert(path, tmp_path / "ds", "local/transport")
    assert dataset.features["observation.state"]["shape"] == (18,)
    assert dataset.features["observation.environment_state"]["shape"] == (41,)
    assert dataset.features["action"]["shape"] == (14,)


def test_filter_key_converts_a_subset(lift_hdf5, tmp_path):
    dataset = convert(lift_hdf5, tmp_path / "ds", "local/lift", filter_key="train")
    assert dataset.meta.total_episodes == 2
    assert dataset.meta.total_frames == LENGTHS["demo_1"] + LENGTHS["demo_10"]


def test_refuses_to_overwrite_without_flag(lift_hdf5, tmp_path):
    out = tmp_path / "ds"
    convert(lift_hdf5, out, "local/lift")
    with pytest.raises(FileExistsError, match="--overwrite"):
        convert(lift_hdf5, out, "local/lift")
    assert convert(lift_hdf5, out, "local/lift", overwrite=True).meta.total_episodes == 3


def test_overwrite_never_deletes_a_foreign_directory(lift_hdf5, tmp_path):
    out = tmp_path / "precious"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="refusing to delete"):
        convert(lift_hdf5, out, "local/lift", overwrite=True)
    assert (out / "notes.txt").exists()


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"filter_key": "valid"}, ValueError, "available filter keys"),
        ({"task": "Stack"}, ValueError, "Unknown robomimic task"),
        ({"task": "TwoArmTransport"}, KeyError, "robot1_eef_pos"),
        ({"obs_type": "image", "camera_names": ["frontview"]}, KeyError, "lacks cameras"),
    ],
)
def test_clear_errors(lift_hdf5, tmp_path, kwargs, error, match):
    with pytest.raises(error, match=match):
        convert(lift_hdf5, tmp_path / "ds", "local/lift", **kwargs)


def test_missing_env_args_needs_task(tmp_path):
    path = write_robomimic(tmp_path / "bare.hdf5", env_args=False, images=False)
    with pytest.raises(ValueError, match="--task"):
        convert(path, tmp_path / "ds", "local/bare")
    assert convert(path, tmp_path / "ds", "local/bare", task="Lift").meta.total_episodes == 3


def test_cli(lift_hdf5, tmp_path, capsys):
    main(["--hdf5", str(lift_hdf5), "--output_dir", str(tmp_path / "ds"), "--obs_type", "low_dim"])
    assert "Wrote 3 episodes (16 frames)" in capsys.readouterr().out


def test_verification_catches_a_changed_value(lift_hdf5, tmp_path, monkeypatch):
    """The read-back check is live: corrupt one written action and conversion must fail."""
    import lerobot_sdp.robomimic.convert as convert_module

    real_make_frame = convert_module.make_frame

    def corrupting_make_frame(obs, action, *args):
        return real_make_frame(obs, np.asarray(action) + 1e-3, *args)

    monkeypatch.setattr(convert_module, "make_frame", corrupting_make_frame)
    with pytest.raises(RuntimeError, match="Conversion changed demo_0 action: 35 of 35 values differ"):
        convert(lift_hdf5, tmp_path / "ds", "local/lift")
