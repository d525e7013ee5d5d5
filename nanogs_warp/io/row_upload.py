"""A PLY file's rows copied to a GPU while the file is still being read.

The reader threads fill the host arrays unit by unit (``ply_read.read_vertex_rows``); each finished
unit's rows are handed to one uploader thread, which copies them into arrays on the device as soon
as the device is known. So the upload (about 0.13 s for a 1 GB file on an H100 host) runs beside
the read instead of after it. The copies run in the driver, outside the interpreter's lock.

What the read changes after a unit is finished is not uploaded: :meth:`RowUpload.splats` uses a
device array only where the final host array is still the one whose rows were copied (the rows of a
file with a suspect value are checked again and may be dropped or normalised anew; infinite opacity
logits are saturated into a new array), and copies the others whole.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable

import numpy as np

_STOP = None
_FIELDS = {"quats_xyzw": "rotations"}  # host array -> SplatSet field, where the names differ


class RowUpload:
    """Receives the host arrays (``begin``) and finished row ranges (``rows``) from the reader, and
    copies them to the device that ``device`` (blocking until it is known, or raising) returns.
    Nothing is copied to the CPU (there the host arrays are shared as they are) unless ``cpu``."""

    def __init__(self, device: Callable, cpu: bool = False):
        self._device = device
        self._cpu = cpu
        self._queue: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._host: dict[str, np.ndarray] = {}
        self._uploaded: dict = {}
        self._failed = False

    def begin(self, arrays: dict[str, np.ndarray]) -> None:
        """The host arrays the reader is about to fill (rows in file order)."""
        self._host = dict(arrays)
        self._thread = threading.Thread(target=self._run, name="nanogs-upload", daemon=True)
        self._thread.start()

    def rows(self, first: int, stop: int) -> None:
        """Rows [first, stop) of every host array are final (as far as the reader knows)."""
        self._queue.put((first, stop))

    def cancel(self) -> None:
        """Stops the uploader (the read failed); what it copied is dropped."""
        if self._thread is not None:
            self._failed = True
            self._queue.put(_STOP)
            self._thread.join()
        self._release()

    def _release(self) -> None:
        """Lets go of the host arrays and the copies: once the caller drops its own references,
        the host memory is free for what comes next (the results' copies back to the host reuse
        it, already mapped: about 0.06 s less for a 600k-splat result than fresh pages)."""
        self._host = {}
        self._uploaded = {}

    def splats(self, arrays: dict[str, np.ndarray], layout):
        """The SplatSet on the device from the final host ``arrays`` (``read_splats``'), using the
        rows copied meanwhile where they still hold; None when nothing was copied (another format,
        the CPU, or a failed start). Afterwards the upload holds no host array (nor copy) of its
        own: the caller's references are the last."""
        if self._thread is None:
            return None
        self._queue.put(_STOP)
        self._thread.join()
        if self._failed or not self._uploaded:
            self._release()
            return None
        from ..splats import SplatSet

        device = next(iter(self._uploaded.values())).device
        n = arrays["means"].shape[0]
        quats_key = "quats_xyzw" if "quats_xyzw" in arrays else None
        final = {
            "means": arrays["means"],
            "rotations": arrays[quats_key] if quats_key else np.ascontiguousarray(arrays["rotations"][:, [1, 2, 3, 0]]),
            "log_scales": arrays["log_scales"],
            "opacities": arrays["opacities"].reshape(n, 1),
            "features": arrays["features"],
            "extras": arrays["extras"].reshape(n, -1),
            "integer_extras": arrays["integer_extras"].reshape(n, -1),
        }
        out = {}
        for field, host in final.items():
            key = "quats_xyzw" if field == "rotations" else field
            copied = self._uploaded.get(key)
            same = key in self._host and host.shape == self._host[key].shape and np.may_share_memory(host, self._host[key])
            if copied is None or not same or (field == "rotations" and quats_key is None):
                copied = _device_array(field, host.shape, device)
                copied.assign(_host_view(field, np.ascontiguousarray(host)))
            out[field] = copied
        out["opacities"] = out["opacities"].reshape((n,))
        self._release()
        return SplatSet(layout=layout, **out)

    def _run(self) -> None:
        try:
            device = self._device()
        except BaseException:  # noqa: BLE001 - the command reports it where it waits for the device
            device = None
        if device is None or (device.is_cpu and not self._cpu):
            self._failed = True
        n = self._host["means"].shape[0] if self._host else 0
        done = False
        try:
            if not self._failed:
                for key, host in self._host.items():
                    self._uploaded[key] = _device_array(_FIELDS.get(key, key), host.shape, device)
            while not done:
                batch = [self._queue.get()]  # and every range finished meanwhile: adjacent ones in one copy
                while True:
                    try:
                        batch.append(self._queue.get_nowait())
                    except queue.Empty:
                        break
                done = _STOP in batch
                if self._failed:
                    continue
                for first, stop in _merged(sorted(r for r in batch if r is not _STOP)):
                    for key, host in self._host.items():
                        if host.size and first < stop <= n:
                            self._uploaded[key][first:stop].assign(_host_view(_FIELDS.get(key, key), host[first:stop]))
        except BaseException:  # noqa: BLE001 - out of device memory, say: the command copies after the read instead
            self._failed = True
            while not done:
                done = self._queue.get() is _STOP


def _merged(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Sorted row ranges with adjacent ones joined."""
    out: list[tuple[int, int]] = []
    for first, stop in ranges:
        if out and out[-1][1] == first:
            out[-1] = (out[-1][0], stop)
        else:
            out.append((first, stop))
    return out


_VECTOR_TYPES = {"means": "vec3", "log_scales": "vec3", "rotations": "quat"}


def _device_array(field: str, shape: tuple, device):
    import warp as wp

    if field in _VECTOR_TYPES:
        return wp.empty(shape[0], dtype=getattr(wp, _VECTOR_TYPES[field]), device=device)
    dtype = wp.int64 if field == "integer_extras" else wp.float32
    return wp.empty(shape, dtype=dtype, device=device)


def _host_view(field: str, rows: np.ndarray):
    """Rows of a host array as a Warp array on the CPU sharing their memory."""
    import warp as wp

    if field in _VECTOR_TYPES:
        return wp.array(rows, dtype=getattr(wp, _VECTOR_TYPES[field]), device="cpu", copy=False)
    return wp.array(rows, dtype=wp.int64 if field == "integer_extras" else wp.float32, device="cpu", copy=False)
