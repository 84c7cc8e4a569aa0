"""`protocol_pickle.loads`: LeRobot's async-inference messages come through whole; a payload that runs
code under plain `pickle.loads` is refused before anything runs."""

import pickle
import time

import numpy as np
import pytest
import torch
from lerobot.async_inference.helpers import RemotePolicyConfig, TimedObservation

from lerobot_sdp.protocol_pickle import UnsafePayloadError, loads


class WritesMarker:
    """Unpickling this calls `exec`, which writes a file: code run by whoever sent the bytes."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').write('ran')",)


def test_lerobot_messages_round_trip():
    raw = {
        "agent_x.pos": np.float64(101.5),
        "block_kp0_x.pos": 3.0,
        "task": "push the T",
        "front": np.arange(12, dtype=np.uint8).reshape(2, 2, 3),
        "wrist": torch.arange(6, dtype=torch.bfloat16).reshape(2, 3),
    }
    sent = TimedObservation(timestamp=time.time(), timestep=7, observation=raw, must_go=True)
    obs = loads(pickle.dumps(sent))
    assert isinstance(obs, TimedObservation) and obs.get_timestep() == 7 and obs.must_go
    back = obs.get_observation()
    assert back["agent_x.pos"] == 101.5 and back["task"] == "push the T"
    np.testing.assert_array_equal(back["front"], raw["front"])
    assert torch.equal(back["wrist"], raw["wrist"]) and back["wrist"].dtype == torch.bfloat16
    features = {"observation.state": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}}
    specs = loads(pickle.dumps(RemotePolicyConfig("sdp", "/ckpt", features, 12, "cpu", {"a": "b"})))
    assert specs == RemotePolicyConfig("sdp", "/ckpt", features, 12, "cpu", {"a": "b"})


def test_a_payload_that_runs_code_under_plain_pickle_is_refused(tmp_path):
    shown = tmp_path / "plain"
    pickle.loads(pickle.dumps(WritesMarker(shown)))  # nosec: the attack, shown
    assert shown.read_text() == "ran"
    marker = tmp_path / "served"
    payload = TimedObservation(timestamp=0.0, timestep=0, observation={"x": WritesMarker(marker)})
    with pytest.raises(UnsafePayloadError, match=r"Refused to unpickle `builtins\.exec`"):
        loads(pickle.dumps(payload))
    assert not marker.exists()


def test_code_hidden_in_a_tensor_storage_is_refused(tmp_path):
    """torch rebuilds a storage with `_load_from_bytes`, a full unpickler; here torch's weights-only one."""
    import io

    inner = io.BytesIO()
    torch.save(WritesMarker(tmp_path / "shown"), inner, _use_new_zipfile_serialization=False)

    class Storage:
        def __reduce__(self):
            return torch.storage._load_from_bytes, (inner.getvalue(),)

    data = pickle.dumps(Storage())
    pickle.loads(data)  # nosec: plain pickle runs it through torch.load(weights_only=False)
    assert (tmp_path / "shown").exists()
    (tmp_path / "shown").unlink()
    with pytest.raises(UnsafePayloadError, match="Cannot read the message"):
        loads(data)
    assert not (tmp_path / "shown").exists()


@pytest.mark.parametrize("data", [b"", b"\x80\x05garbage", pickle.dumps(TimedObservation(0.0, 0, {}))[:-5]])
def test_broken_bytes_are_a_clear_error(data):
    with pytest.raises(UnsafePayloadError, match="Cannot read the message"):
        loads(data)
