"""Replay buffer that stores every rendered frame once and stacks at sample time.

Layout: one *slot* per observation.  Slot ``i`` holds the newest frame of
observation ``o_i`` (``3 x H x W`` uint8), the action taken from it, the reward
and discount that followed, and ``step_in_episode[i]``.  A transition
``(o_i, a_i, r_i, o_{i+1})`` is therefore the slot pair ``(i, i+1)`` and costs one
frame plus a few scalars (about 30 KB at 100x100) instead of two stacked
observations (180 KB).  The stack of ``o_i`` is the frames of slots
``i-k+1 .. i``, with offsets clamped at the episode's first slot so a stack
never mixes episodes (the first frame repeats, as the env does on reset).

Slots are written in a ring.  A slot ``i`` can start a transition when ``i+1``
is live (not the write head) and every frame of its stack is still live.

With ``physics_dim > 0`` each slot also keeps the simulator state its frame was rendered
from (``physics[i]``, float64, dm_control's ``physics.get_state()``) and the agent step at
which it was stored (``agent_step[i]``), so that ``imssr analyze`` can render the very same
states again under other nuisances and place them in the true state space: 8 bytes per state
coordinate + 4 per slot (cartpole +20 B, walker +76 B on a 30 KB frame).  Slots whose state
was not recorded (loaded from a replay file written before this) hold NaN and step -1.

Saved, the buffer is an index (``.npz``: the per-slot fields, the ring's position and the list of
frame files with their sha256) and frame files that each hold the frames written between two
saves (``replay-frames-<first>-<end>.npy``, frames counted from the buffer's first write).  A save
writes only the frames written since the previous save into the same directory, and a new index;
the frame files the index names are those still holding a live frame.  So the bytes a run writes
for its checkpoints grow with its length, not with its square.

An update takes its batch from :meth:`FrameReplayBuffer.sample_batch`: tensors on the agent's
device, gathered on the host into one staging buffer (pinned for a GPU) and copied once.
:class:`imssr.replay.device.TensorFrameReplayBuffer` keeps the frames on the device instead and
gathers them there; both draw the same indices and write the same files.
"""
from __future__ import annotations

import errno
import hashlib
import math
import os
import warnings
from typing import Optional

import numpy as np
import torch

from imssr.errors import ImssrError
from imssr.files import atomic_path, disk_full_as_error, open_own
from imssr.integrity import UNSEALED, HashingWriter, seal_zip, zip_seal_problem
from imssr.memlimit import proc_bytes


CHUNK_FILE = "replay-frames-{first:012d}-{end:012d}.npy"
"""A frame file: the frames written ``first`` to ``end - 1`` (counted from the buffer's first write)."""


def chunk_path(directory: str, first: int, end: int) -> str:
    """The frame file of the frames ``first`` to ``end - 1`` in ``directory``."""
    return os.path.join(directory, CHUNK_FILE.format(first=first, end=end))


def replay_files(path: str) -> list[str]:
    """The files of the buffer saved as ``path``: the index and the frame files it names (for an
    index written before frame files: the single frames file).  :class:`ReplayFileError` when the
    index is missing or cannot be read and verified, since what it names is then unknown."""
    _verify_index(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            if "frame_chunks" not in data.files:
                return [path, frames_path(path)]
            directory = os.path.dirname(path)
            return [path] + [chunk_path(directory, int(a), int(b)) for a, b in data["frame_chunks"]]
    except Exception as exc:  # noqa: BLE001 - zip/npy corruption has many faces
        raise ReplayFileError(f"corrupt replay buffer file {path}: {type(exc).__name__}: {exc}") from None


def _verify_index(path: str) -> None:
    """Check the seal of the replay index ``path`` (:mod:`imssr.integrity`) before anything reads
    it: :class:`ReplayFileError` when it is missing, unreadable, damaged or carries no seal (imssr
    seals every index it writes, so such a file is not one of its buffers)."""
    if not os.path.exists(path):
        raise ReplayFileError(f"replay buffer file not found: {path}")
    try:
        problem = zip_seal_problem(path)
    except OSError as exc:
        raise ReplayFileError(f"cannot read replay buffer file {path}: {exc.strerror or exc}") from None
    if problem == UNSEALED:
        raise ReplayFileError(f"{path} is not a replay buffer imssr wrote: it carries no imssr checksum")
    if problem is not None:
        raise ReplayFileError(f"replay buffer {path} is damaged ({problem})")


def frames_path(path: str) -> str:
    """Where :meth:`FrameReplayBuffer.save` puts the frames that go with ``path``."""
    return path + ".frames.npy"


class ReplayFileError(ImssrError):
    """A saved replay buffer that is missing, unreadable or damaged (a resume may refill instead)."""


class ReplayMemoryWarning(UserWarning):
    """The replay buffer may not fit in memory (shown by default, unlike ResourceWarning)."""


def available_memory_bytes() -> Optional[int]:
    """``MemAvailable`` from /proc/meminfo, or None where it cannot be read."""
    return proc_bytes("/proc/meminfo", "MemAvailable")


class FrameReplayBuffer:
    """Preallocated uint8 ring of frames with per-slot transition fields.

    Args:
        capacity: number of slots (stored observations).  An episode of ``n``
            transitions uses ``n + 1`` slots.
        frame_shape: ``(C, H, W)`` of one rendered frame.
        action_dim: size of the action vector.
        frame_stack: frames per observation.
        seed: seed of the sampling generator.
        physics_dim: length of the recorded physics state (0: none recorded).
    """

    def __init__(self, capacity: int, frame_shape: tuple[int, int, int], action_dim: int,
                 frame_stack: int = 3, seed: int = 0, warn_memory: bool = True, physics_dim: int = 0):
        if capacity < 2:
            raise ImssrError(f"replay capacity must be >= 2, got {capacity}")
        self.capacity = int(capacity)
        self.frame_shape = tuple(frame_shape)
        self.action_dim = int(action_dim)
        self.frame_stack = int(frame_stack)
        self.physics_dim = int(physics_dim)
        if warn_memory:
            need, avail = self.host_nbytes_expected(), available_memory_bytes()
            if avail is not None and need > avail:
                warnings.warn(
                    f"replay buffer of {capacity} slots needs {need / 2**30:.1f} GiB but only "
                    f"{avail / 2**30:.1f} GiB is available; lower the replay capacity",
                    ReplayMemoryWarning, stacklevel=2)
        self.frames = self._allocate_frames()
        self.actions = np.zeros((self.capacity, self.action_dim), dtype=np.float32)
        self.rewards = np.zeros((self.capacity,), dtype=np.float32)
        self.discounts = np.ones((self.capacity,), dtype=np.float32)
        self.step_in_episode = np.zeros((self.capacity,), dtype=np.int32)
        # Zeros, not NaN/-1 fills: pages are committed only as slots are written.
        self.physics = np.zeros((self.capacity if self.physics_dim else 0, self.physics_dim), dtype=np.float64)
        self.agent_step = np.zeros((self.capacity if self.physics_dim else 0,), dtype=np.int32)
        self.head = 0  # next slot to write
        self.size = 0  # live slots
        self.written = 0  # frames ever written: frame k sits in slot k % capacity
        # The frame files of the last save or load that still hold live frames, as
        # (first, end, sha256), and their directory: the next save there writes only newer frames.
        self._chunks: list[tuple[int, int, str]] = []
        self._chunks_dir: Optional[str] = None
        self.rng = np.random.default_rng(seed)
        self._open_episode = False

    # -- memory ----------------------------------------------------------------
    def bytes_per_slot(self) -> int:
        physics = 8 * self.physics_dim + 4 if self.physics_dim else 0  # state + agent step
        return self.frame_nbytes() + 4 * self.action_dim + 4 + 4 + 4 + physics

    def nbytes_expected(self) -> int:
        return self.capacity * self.bytes_per_slot()

    def frame_nbytes(self) -> int:
        """Bytes of one stored frame."""
        return int(np.prod(self.frame_shape))

    def host_nbytes_expected(self) -> int:
        """What the buffer takes in host memory when full (all of it: the frames live here)."""
        return self.nbytes_expected()

    def _allocate_frames(self):
        # np.empty/zeros map pages lazily: memory is committed as frames arrive.
        try:
            return np.zeros((self.capacity, *self.frame_shape), dtype=np.uint8)
        except (MemoryError, ValueError):  # ValueError: more than a process can address
            raise ImssrError(
                f"cannot allocate a replay buffer of {self.nbytes_expected() / 2**30:.1f} GiB "
                f"({self.capacity} transitions); lower the replay capacity (--replay-capacity)") from None

    # -- writing ---------------------------------------------------------------
    def add_first(self, frame: np.ndarray, physics: Optional[np.ndarray] = None, agent_step: int = -1) -> None:
        """Start an episode with the newest frame of its first observation (and, for a buffer
        with ``physics_dim``, the physics state it shows and the agent step it was stored at)."""
        self._write(frame, step=0, physics=physics, agent_step=agent_step)
        self._open_episode = True

    def add(self, action: np.ndarray, reward: float, discount: float, next_frame: np.ndarray,
            physics: Optional[np.ndarray] = None, agent_step: int = -1) -> None:
        """Record the transition out of the newest observation and the next frame.

        ``discount`` is 0 for a true terminal state and 1 otherwise (a time
        limit is not terminal: the critic keeps bootstrapping).  ``physics`` and
        ``agent_step`` go with ``next_frame``, as in :meth:`add_first`.
        """
        if not self._open_episode:
            raise RuntimeError("add_first() must start an episode before add()")
        last = (self.head - 1) % self.capacity
        self.actions[last] = action
        self.rewards[last] = reward
        self.discounts[last] = discount
        self._write(next_frame, step=int(self.step_in_episode[last]) + 1, physics=physics, agent_step=agent_step)

    def _write(self, frame: np.ndarray, step: int, physics: Optional[np.ndarray], agent_step: int) -> None:
        self._write_frame(self.head, frame)
        self.step_in_episode[self.head] = step
        if self.physics_dim:
            self.physics[self.head] = np.nan if physics is None else physics
            self.agent_step[self.head] = agent_step
        self.head = (self.head + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.written += 1

    def _write_frame(self, slot: int, frame: np.ndarray) -> None:
        self.frames[slot] = frame

    # -- sampling --------------------------------------------------------------
    def _valid(self, idx: np.ndarray) -> np.ndarray:
        oldest = (self.head - self.size) % self.capacity
        age = (idx - oldest) % self.capacity  # 0 = oldest live slot
        newest = self.size - 1
        history = np.minimum(self.frame_stack - 1, self.step_in_episode[idx])
        nxt = (idx + 1) % self.capacity
        same_episode = self.step_in_episode[nxt] == self.step_in_episode[idx] + 1
        return (age < newest) & (age >= history) & same_episode

    def live_slots(self) -> np.ndarray:
        """Indices of the live slots, oldest first."""
        return (self.head - self.size + np.arange(self.size)) % self.capacity

    def num_transitions(self) -> int:
        if self.size < 2:
            return 0
        return int(self._valid(self.live_slots()).sum())

    def sample_indices(self, batch_size: int) -> np.ndarray:
        """Uniform over valid transitions (rejection sampling over live slots)."""
        if self.size < 2:
            raise ImssrError("replay buffer holds no complete transition yet")
        oldest = (self.head - self.size) % self.capacity
        out = np.empty(0, dtype=np.int64)
        rounds = 0
        # Almost every live slot starts a valid transition, so this loops once.
        while out.size < batch_size:
            cand = (oldest + self.rng.integers(0, self.size, size=2 * batch_size)) % self.capacity
            out = np.concatenate([out, cand[self._valid(cand)]])
            rounds += 1
            if rounds == 8 and out.size < batch_size and self.num_transitions() == 0:
                raise ImssrError("replay buffer holds no complete transition yet")
        return out[:batch_size]

    def stack_indices(self, idx: np.ndarray) -> np.ndarray:
        """Slots of the frames of ``o_i`` and ``o_{i+1}``: shape ``(B, frame_stack + 1)``.

        Offsets below the episode's first slot are clamped to it.  The same
        clamp serves ``o_{i+1}`` because its episode starts at the same slot.
        """
        k = np.arange(-(self.frame_stack - 1), 2)  # e.g. -2, -1, 0, +1
        offs = np.maximum(k[None, :], -self.step_in_episode[idx][:, None])
        return (idx[:, None] + offs) % self.capacity

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """A batch of stacked transitions as numpy arrays (``obs`` is uint8)."""
        return self.gather(self.sample_indices(batch_size))

    def sample_batch(self, batch_size: int, device: str | torch.device) -> dict[str, torch.Tensor]:
        """:meth:`sample` as tensors on ``device`` (what an update consumes): the same draws of
        the sampling generator and the same values, for every store."""
        return self.gather_batch(self.sample_indices(batch_size), torch.device(device))

    def gather_batch(self, idx: np.ndarray, device: torch.device) -> dict[str, torch.Tensor]:
        """The host path: the frame windows and the transition fields are gathered straight into
        one staging buffer, pinned when ``device`` is CUDA, and cross to the device in a single
        ``non_blocking`` copy (the host goes on meanwhile; the caching host allocator keeps the
        pinned block until the copy has run).  On the CPU the staging buffer is the batch."""
        idx = np.asarray(idx, dtype=np.int64)
        b = len(idx)
        packing = self._packing(b, torch.uint8, (b * (self.frame_stack + 1), *self.frame_shape))
        host = packing.host_buffer(pin=device.type == "cuda")
        frames, *fields = packing.views(host)
        slots = torch.from_numpy(self.stack_indices(idx).reshape(-1))
        torch.index_select(torch.from_numpy(self.frames), 0, slots, out=frames)
        self._gather_fields(idx, *fields)
        return self._batch(*packing.views(host.to(device, non_blocking=True)))

    def _packing(self, b: int, first_dtype: torch.dtype, first_shape: tuple[int, ...]) -> "Packing":
        """The staging layout of a batch of ``b``: a first field (the frames, or the slots a
        store on the device gathers them from), then action, reward and discount."""
        return Packing([(first_dtype, first_shape), (torch.float32, (b, self.action_dim)),
                        (torch.float32, (b,)), (torch.float32, (b,))])

    def _gather_fields(self, idx: np.ndarray, action: torch.Tensor, reward: torch.Tensor,
                       discount: torch.Tensor) -> None:
        rows = torch.from_numpy(idx)
        for source, out in ((self.actions, action), (self.rewards, reward), (self.discounts, discount)):
            torch.index_select(torch.from_numpy(source), 0, rows, out=out)

    def _batch(self, frames: torch.Tensor, action: torch.Tensor, reward: torch.Tensor,
               discount: torch.Tensor) -> dict[str, torch.Tensor]:
        """``obs`` and ``next_obs`` as views of one window of ``frame_stack + 1`` frames per
        sample (the strides :meth:`gather`'s arrays have)."""
        b, (c, h, w) = len(action), self.frame_shape
        window = frames.view(b, self.frame_stack + 1, c, h, w)
        return {
            "obs": window[:, :-1].reshape(b, self.frame_stack * c, h, w),
            "action": action,
            "reward": reward,
            "discount": discount,
            "next_obs": window[:, 1:].reshape(b, self.frame_stack * c, h, w),
        }

    def gather(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """The transitions ``idx`` as numpy arrays (``obs`` is uint8): :meth:`gather_batch` on the CPU."""
        return {k: v.numpy() for k, v in self.gather_batch(idx, torch.device("cpu")).items()}

    # -- persistence -------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"head": self.head, "size": self.size, "open": self._open_episode,
                "rng": self.rng.bit_generator.state}

    def save(self, path: str) -> None:
        """Write the live contents atomically: the frames written since the last save into
        ``path``'s directory as a new frame file (:data:`CHUNK_FILE`), then the index ``path``
        (``.npz``: small fields, the ring's position, the frame files that hold live frames and
        the sha256 of each).  The frame files of earlier saves stay as they are and are named
        again while they hold a live frame; the ``.npz`` is sealed with its own sha256
        (:mod:`imssr.integrity`).  :meth:`load` verifies every file it reads.
        """
        directory = os.path.dirname(os.path.abspath(path))
        live_from = self.written - self.size
        chunks = [c for c in self._chunks if c[1] > live_from] if self._chunks_dir == directory else []
        if not all(os.path.exists(chunk_path(directory, a, b)) for a, b, _ in chunks):
            chunks = []  # a frame file was removed: write every live frame again
        first = chunks[-1][1] if chunks else live_from
        if first < self.written:
            chunks.append((first, self.written, self._save_chunk(directory, first, self.written)))
        n = self.capacity if self.size == self.capacity else self.head  # slots ever written
        small = {"actions": self.actions[:n], "rewards": self.rewards[:n], "discounts": self.discounts[:n],
                 "step_in_episode": self.step_in_episode[:n]}
        if self.physics_dim:
            small.update(physics=self.physics[:n], agent_step=self.agent_step[:n])
        with atomic_path(path, needed=sum(x.nbytes for x in small.values()) + 4096 + 100 * len(chunks)) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **small,
                         meta=np.array([self.capacity, self.head, self.size, int(self._open_episode), self.written]),
                         frame_shape=np.array(self.frame_shape),
                         frame_chunks=np.array([(a, b) for a, b, _ in chunks], dtype=np.int64).reshape(-1, 2),
                         frame_chunk_sha256=np.array([h for _, _, h in chunks], dtype="<U64"))
            seal_zip(tmp)
        self._chunks, self._chunks_dir = chunks, directory

    def _save_chunk(self, directory: str, first: int, end: int) -> str:
        """Write frames ``first`` to ``end - 1`` as one ``.npy`` frame file; returns its sha256."""
        n = end - first
        with atomic_path(chunk_path(directory, first, end), needed=n * self.frame_nbytes() + 128) as tmp:
            with open(tmp, "wb") as fh:
                # Through a writer that is not a file, hashed on the way (numpy's tofile() would
                # lose a full disk's errno); the header is np.save's for this shape.
                writer = HashingWriter(fh)
                np.lib.format.write_array_header_1_0(writer, {
                    "descr": np.lib.format.dtype_to_descr(np.dtype(np.uint8)), "fortran_order": False,
                    "shape": (n, *self.frame_shape)})
                for slot, count in self._slot_runs(first, end):
                    self._write_slots(writer, slot, count)
        return writer.digest

    def _slot_runs(self, first: int, end: int) -> list[tuple[int, int]]:
        """Frames ``first`` to ``end - 1`` as runs of consecutive slots ``(slot, count)``."""
        runs, k = [], first
        while k < end:
            slot = k % self.capacity
            count = min(end - k, self.capacity - slot)
            runs.append((slot, count))
            k += count
        return runs

    def _write_slots(self, writer: HashingWriter, slot: int, count: int) -> None:
        """The frames of slots ``slot`` to ``slot + count - 1``, raw, to ``writer``."""
        fb = self.frame_nbytes()
        writer.write(memoryview(self.frames).cast("B")[slot * fb:(slot + count) * fb])  # a view: no copy

    def load(self, path: str, rng_state: Optional[dict] = None) -> None:
        """Load what :meth:`save` wrote, verifying its checksums; :class:`ReplayFileError` when
        a file is missing, damaged or carries no checksum."""
        _verify_index(path)
        try:
            # Arrays only: an object array in a replay file someone else wrote would unpickle.
            with np.load(path, allow_pickle=False) as data:
                meta = [int(x) for x in data["meta"]]
                capacity, head, size, open_ = meta[:4]
                # Files written before the counter: any count that puts the head where it is.
                written = meta[4] if len(meta) > 4 else (head if size < capacity else capacity + head)
                if capacity != self.capacity or tuple(data["frame_shape"]) != self.frame_shape:
                    raise ImssrError(
                        f"replay buffer {path} has capacity {capacity} and frames "
                        f"{tuple(data['frame_shape'])}, expected {self.capacity} and {self.frame_shape}")
                n = data["actions"].shape[0]
                for name in ("actions", "rewards", "discounts", "step_in_episode"):
                    getattr(self, name)[:n] = data[name]
                self._read_physics(data, path, n)
                directory, chunks = os.path.dirname(os.path.abspath(path)), []
                if "frame_chunks" in data.files:
                    chunks = [(int(a), int(b), str(h)) for (a, b), h in
                              zip(data["frame_chunks"], data["frame_chunk_sha256"], strict=True)]
                    self._read_chunks(path, directory, chunks, written - size, written)
                elif "frames_sha256" in data.files:  # from before frame files: one file, the ring's first slots
                    self._read_frame_file(frames_path(path), n, str(data["frames_sha256"]), 0, [(0, n)])
                else:
                    raise ReplayFileError(f"replay buffer {path} holds no checksum of its frames")
        except ImssrError:
            raise
        except Exception as exc:  # noqa: BLE001 - zip/npy corruption has many faces
            raise ReplayFileError(f"corrupt replay buffer file {path}: {type(exc).__name__}: {exc}") from None
        self.head, self.size, self._open_episode, self.written = head, size, bool(open_), written
        self._chunks, self._chunks_dir = chunks, directory
        if rng_state is not None:
            self.rng.bit_generator.state = rng_state

    def _read_chunks(self, path: str, directory: str, chunks: list[tuple[int, int, str]],
                     live_from: int, written: int) -> None:
        """Read the live frames (``live_from`` to ``written - 1``) from the frame files the index
        ``path`` names, each verified against its sha256."""
        covered = live_from
        for first, end, _ in chunks:
            if first > covered or end <= first:
                break
            covered = max(covered, end)
        if (chunks and chunks[0][0] > live_from) or covered < written:
            raise ReplayFileError(f"replay buffer {path} does not name frame files for all its frames")
        for first, end, expected in chunks:
            dead = max(0, min(live_from, end) - first)  # frames the ring has overwritten since
            self._read_frame_file(chunk_path(directory, first, end), end - first, expected, dead,
                                  self._slot_runs(first + dead, end))

    def _read_frame_file(self, fpath: str, n: int, expected: str, dead: int, runs: list[tuple[int, int]]) -> None:
        """Read the frame file ``fpath`` of ``n`` frames, hashing all of it to check its sha256
        ``expected``: its first ``dead`` frames are hashed only, the others go to the slot ``runs``
        (``(slot, count)``)."""
        if not os.path.exists(fpath):
            raise ReplayFileError(f"replay buffer file not found: {fpath}")
        h = hashlib.sha256()
        with open(fpath, "rb") as fh:
            self._read_npy_header(fh, h, fpath, n)
            _skip_hashed(fh, h, dead * self.frame_nbytes(), fpath)
            for slot, count in runs:
                self._read_slots(fh, h, slot, count, fpath)
            if fh.read(1):
                raise ReplayFileError(f"replay frames {fpath} have trailing bytes")
        if h.hexdigest() != expected:
            raise ReplayFileError(f"replay buffer {fpath} is damaged (checksum mismatch)")

    def _read_npy_header(self, fh, h, fpath: str, n: int) -> None:
        """Read a frame file's ``.npy`` header (hashed into ``h``); it must describe ``n`` frames."""
        try:
            version = np.lib.format.read_magic(fh)
            if version != (1, 0):  # what np.save and _save_chunk write for frames
                raise ValueError(f"npy format version {version}")
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        except Exception as exc:  # noqa: BLE001 - numpy's header parser fails in many ways
            # Named here: the index that lists this file is whole (its seal verified).
            what = "empty" if not fh.tell() else f"its .npy header is unreadable: {exc}"
            raise ReplayFileError(f"replay frames {fpath} are damaged ({what})") from None
        end = fh.tell()
        fh.seek(0)
        h.update(fh.read(end))
        if shape != (n, *self.frame_shape) or fortran or dtype != np.uint8:
            raise ReplayFileError(f"replay frames {fpath} have shape {shape} ({dtype}), "
                                  f"expected {(n, *self.frame_shape)} (uint8)")

    def _read_physics(self, data, path: str, n: int) -> None:
        """The recorded physics states and agent steps of a file; a file written before they
        were recorded (or by a buffer without them) leaves NaN states and step -1."""
        if not self.physics_dim:
            return
        if "physics" not in data.files:
            self.physics[:n] = np.nan
            self.agent_step[:n] = -1
            return
        if data["physics"].shape != (n, self.physics_dim):
            raise ImssrError(f"replay buffer {path} has physics states of shape {data['physics'].shape}, "
                             f"expected {(n, self.physics_dim)}")
        self.physics[:n] = data["physics"]
        self.agent_step[:n] = data["agent_step"]

    def _read_slots(self, fh, h, slot: int, count: int, fpath: str) -> None:
        """``count`` frames from ``fh`` into slots ``slot`` onwards, hashed into ``h`` (peak memory
        beyond the ring: one read)."""
        fb = self.frame_nbytes()
        read_hashed(fh, h, memoryview(self.frames).cast("B")[slot * fb:(slot + count) * fb], fpath)

    def __len__(self) -> int:
        return self.size

    def close(self) -> None:
        """Give up what the store holds outside the process (nothing, for frames in memory)."""


class DiskFrameReplayBuffer(FrameReplayBuffer):
    """The frame store as a file on local disk, memory-mapped (``train.replay_device=disk``): the
    kernel's page cache keeps the frames that memory allows and reads the others back, so a batch
    of runs whose frames outgrow host memory still trains.  The frames are the same bytes in the
    same slots, so the batches, the saved files and a resume are the in-memory store's.  The file
    is scratch (the checkpoints' replay files are the record): made (or replaced) when the buffer
    is, removed by :meth:`close`.

    Args:
        path: the frames file (:meth:`imssr.rundir.RunDir.frames_file`); one there is replaced.
        reserve_slots: frames whose disk space is set aside at once (``posix_fallocate``): a file
            system that fills up later cannot fail a write into the mapping (which the kernel
            answers with SIGBUS, not an error).  The other arguments are
            :class:`FrameReplayBuffer`'s.
    """

    def __init__(self, *args, path: str, reserve_slots: int = 0, **kwargs):
        self.path, self.reserve_slots = path, reserve_slots
        super().__init__(*args, **kwargs)

    def host_nbytes_expected(self) -> int:
        return self.nbytes_expected() - self.capacity * self.frame_nbytes()

    def _allocate_frames(self):
        size = self.capacity * self.frame_nbytes()
        reserve = min(self.reserve_slots, self.capacity) * self.frame_nbytes()
        with disk_full_as_error(self.path, reserve):
            fd = open_own(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC)
            try:
                os.ftruncate(fd, size)  # sparse: blocks are taken as frames are written
                if reserve:
                    try:
                        os.posix_fallocate(fd, 0, reserve)
                    except OSError as exc:
                        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                            raise
            finally:
                os.close(fd)
        return np.memmap(self.path, dtype=np.uint8, mode="r+", shape=(self.capacity, *self.frame_shape))

    def close(self) -> None:
        """Remove the frames file (idempotent); the mapping, and the disk space with it, goes with
        the buffer."""
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


READ_CHUNK = 1 << 24
"""Bytes per read when loading frames (peak memory beyond the ring: one chunk at most)."""


def read_hashed(fh, h, out: memoryview, fpath: str) -> None:
    """Fill ``out`` from ``fh`` in :data:`READ_CHUNK` reads, hashing what arrives into ``h``."""
    pos, total = 0, len(out)
    while pos < total:
        got = fh.readinto(out[pos:min(pos + READ_CHUNK, total)])
        if not got:
            raise ReplayFileError(f"replay frames {fpath} are truncated")
        h.update(out[pos:pos + got])
        pos += got


def _skip_hashed(fh, h, nbytes: int, fpath: str) -> None:
    """Read ``nbytes`` from ``fh`` into ``h`` only, one :data:`READ_CHUNK` at a time (frames of a
    file that the ring has overwritten since: hashed, not kept)."""
    scratch = memoryview(bytearray(min(nbytes, READ_CHUNK)))
    while nbytes > 0:
        size = min(nbytes, len(scratch))
        read_hashed(fh, h, scratch[:size], fpath)
        nbytes -= size


ALIGN = 8
"""Byte alignment of every field in a :class:`Packing`: int64 slots and float32 fields are then
viewed in place from the raw bytes."""


class Packing:
    """Typed fields laid out one after another in one uint8 buffer: filled on the host, moved in
    one copy, and viewed as the same typed tensors wherever the bytes went."""

    def __init__(self, fields: list[tuple[torch.dtype, tuple[int, ...]]]):
        self.fields = fields
        self.offsets, pos = [], 0
        for dtype, shape in fields:
            self.offsets.append(pos)
            pos += -(-math.prod(shape) * dtype.itemsize // ALIGN) * ALIGN
        self.nbytes = pos

    def host_buffer(self, pin: bool) -> torch.Tensor:
        """A host buffer for the fields; ``pin``: in page-locked memory (for a ``non_blocking``
        copy to a GPU)."""
        return torch.empty(self.nbytes, dtype=torch.uint8, pin_memory=pin)

    def views(self, buf: torch.Tensor) -> list[torch.Tensor]:
        """The fields as typed views of ``buf`` (a buffer of :attr:`nbytes`, on any device)."""
        out = []
        for (dtype, shape), offset in zip(self.fields, self.offsets, strict=True):
            nbytes = math.prod(shape) * dtype.itemsize
            out.append(buf[offset:offset + nbytes].view(dtype).view(shape))
        return out
