"""Reading the bytes LeRobot's async-inference clients send, admitting only the protocol's own types.

LeRobot 0.6.1's transport pickles its messages and its server `pickle.loads` them. A pickle can name
any importable callable and have it called while loading, so plain `pickle.loads` lets anyone who
can reach the server's port run code on the robot's computer. `loads` reads the same bytes with an
`Unpickler` whose `find_class` admits only the globals LeRobot's messages are made of: the message
classes (`TimedObservation`, `RemotePolicyConfig`), numpy arrays and scalars, torch tensors and
`OrderedDict`. Anything else is refused with `UnsafePayloadError`, naming the global.

Torch pickles a tensor's storage as `torch.storage._load_from_bytes(bytes)`, which unpickles those
nested bytes with a plain unpickler; here the storage is read with `torch.load(weights_only=True)`,
torch's own restricted loader, instead.
"""

import io
import pickle  # nosec: only ever with RestrictedUnpickler below
from typing import Any

import torch


def _load_storage(data: bytes) -> Any:
    return torch.load(io.BytesIO(data), weights_only=True)


_ADMITTED = {
    ("lerobot.async_inference.helpers", "TimedObservation"): None,
    ("lerobot.async_inference.helpers", "RemotePolicyConfig"): None,
    ("collections", "OrderedDict"): None,
    ("numpy", "ndarray"): None,
    ("numpy", "dtype"): None,
    ("numpy._core.multiarray", "_reconstruct"): None,  # numpy >= 2
    ("numpy._core.multiarray", "scalar"): None,
    ("numpy.core.multiarray", "_reconstruct"): None,  # numpy 1.x
    ("numpy.core.multiarray", "scalar"): None,
    ("torch._utils", "_rebuild_tensor_v2"): None,
    ("torch.storage", "_load_from_bytes"): _load_storage,
}


class UnsafePayloadError(pickle.UnpicklingError):
    """Client bytes that are not one of LeRobot's async-inference messages."""


class RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ADMITTED:
            raise UnsafePayloadError(
                f"Refused to unpickle `{module}.{name}`: this server reads only LeRobot's async-inference "
                "messages (TimedObservation, RemotePolicyConfig, with numbers, numpy arrays and tensors). "
                "Send observations with LeRobot's RobotClient."
            )
        return _ADMITTED[module, name] or super().find_class(module, name)


def loads(data: bytes) -> Any:
    """`pickle.loads` for untrusted client bytes: LeRobot's message types only (module docstring)."""
    try:
        return RestrictedUnpickler(io.BytesIO(data)).load()
    except UnsafePayloadError:
        raise
    except Exception as e:  # truncated or corrupt bytes: pickle raises anything from EOFError to KeyError
        raise UnsafePayloadError(f"Cannot read the message ({type(e).__name__}: {e}).") from e
