"""Chunk files of an ensemble run: written atomically, checked when read back.

An output directory holds `run.json` (what the run is: a fingerprint of its settings, `n`, the
chunk size) and one `chunk-NNNNNN.npz` per finished chunk. A chunk file is written to a
temporary name in the same directory, flushed to disk and renamed (atomic on POSIX), so a
crash leaves either the whole file or none. Each file records the run's fingerprint, its chunk
index and a SHA-256 of its arrays; a file that cannot be read, belongs to another run or fails
its checksum is reported and computed again.
"""

import hashlib
import json
import os
import socket
import tempfile
from pathlib import Path

import numpy as np

from ._errors import warn
from ._validation import ParameterError

_FORMAT = 1


def digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


_HOST = socket.gethostname().replace(".", "_")


def _atomic_write(path: Path, write) -> None:
    # The temporary name carries the writer's host and process, so that another process
    # opening the same directory can tell a write in progress from one that died.
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{_HOST}.{os.getpid()}.",
                               suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class ChunkStore:
    """The chunk files of one run in `directory`."""

    def __init__(self, directory: str | os.PathLike, description: dict, n: int, chunk_size: int):
        self.directory = Path(directory)
        if self.directory.exists() and not self.directory.is_dir():
            raise ParameterError(f"out={str(directory)!r}: exists and is not a directory")
        self.directory.mkdir(parents=True, exist_ok=True)
        text = json.dumps(description, sort_keys=True, default=str)
        self.fingerprint = hashlib.sha256(text.encode()).hexdigest()
        manifest = {"format": _FORMAT, "fingerprint": self.fingerprint, "n": n,
                    "chunk_size": chunk_size, "settings": description}
        path = self.directory / "run.json"
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except (OSError, ValueError):
                old = None
            if old is None or not isinstance(old, dict):
                raise ParameterError(
                    f"out={str(directory)!r}: run.json is unreadable: delete the directory or "
                    "use another one")
            if (old.get("fingerprint"), old.get("n"), old.get("chunk_size")) != (
                    self.fingerprint, n, chunk_size):
                raise ParameterError(
                    f"out={str(directory)!r} holds a different run (other settings, n or "
                    "chunk size): use another directory, or delete it to start again")
        else:
            _atomic_write(path, lambda f: f.write(
                json.dumps(manifest, indent=1, sort_keys=True, default=str).encode()))
        for entry in self.directory.glob("chunk-*.npz"):
            if not entry.is_file():
                raise ParameterError(
                    f"out={str(directory)!r}: {entry.name} is not a chunk file (a "
                    f"{'directory' if entry.is_dir() else 'special file'}): move it away or "
                    "use another directory")
        self._remove_dead_temporaries()
        self.recomputed: list[int] = []

    @classmethod
    def existing(cls, directory: str | os.PathLike) -> "ChunkStore":
        """The store of a run already in `directory` (its `run.json`), opened to read its
        chunks: nothing is written or removed."""
        path = Path(directory) / "run.json"
        if not path.is_file():
            raise ParameterError(f"{str(directory)!r} holds no ensemble run (no run.json): "
                                 "give the directory of jaxdyn montecarlo --out or "
                                 "jd.ensemble(..., out=)")
        try:
            manifest = json.loads(path.read_text())
            n, chunk_size = int(manifest["n"]), int(manifest["chunk_size"])
            fingerprint = str(manifest["fingerprint"])
        except (OSError, ValueError, KeyError, TypeError):
            raise ParameterError(f"{path}: unreadable run description") from None
        store = cls.__new__(cls)
        store.directory, store.fingerprint = Path(directory), fingerprint
        store.n, store.chunk_size, store.settings = n, chunk_size, manifest.get("settings", {})
        store.recomputed = []
        return store

    def _remove_dead_temporaries(self) -> None:
        """Temporary files of writes that died: only those of a process of this host that no
        longer runs (another process, here or on another host, may be writing into this
        directory at this moment). Each removal is named in a warning."""
        for tmp in self.directory.glob(".chunk-*.tmp"):
            parts = tmp.name.split(".")
            # .chunk-NNNNNN.npz.<host>.<pid>.<random>.tmp
            if len(parts) < 6 or parts[-4] != _HOST or not parts[-3].isdigit():
                continue
            pid = int(parts[-3])
            if pid == os.getpid() or _alive(pid):
                continue
            try:
                tmp.unlink()
            except FileNotFoundError:
                continue
            warn(f"removed {tmp}: the unfinished write of process {pid}, which no longer "
                 "runs")

    def path(self, index: int) -> Path:
        return self.directory / f"chunk-{index:06d}.npz"

    def write(self, index: int, arrays: dict[str, np.ndarray]) -> None:
        meta = {"fingerprint": self.fingerprint, "index": index, "sha256": digest(arrays)}
        payload = {f"data/{k}": np.asarray(v) for k, v in arrays.items()}
        payload["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        _atomic_write(self.path(index), lambda f: np.savez(f, **payload))

    def exists(self, index: int) -> bool:
        return self.path(index).exists()

    def read(self, index: int) -> dict[str, np.ndarray] | None:
        """The chunk's arrays, or `None` if it is missing or fails its checks (then a warning
        says why, and the chunk is listed in `recomputed`)."""
        path = self.path(index)
        if not path.exists():
            return None
        why = None
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(bytes(f["meta"]).decode())
                arrays = {k[len("data/"):]: f[k] for k in f.files if k.startswith("data/")}
        except Exception as e:  # any unreadable file (truncated zip, bad header) is recomputed
            why = f"unreadable ({type(e).__name__}: {e})"
        else:
            if not isinstance(meta, dict):
                why = "not a jaxdyn chunk file (its meta is not a record)"
            elif meta.get("fingerprint") != self.fingerprint or meta.get("index") != index:
                why = "written by another run"
            elif meta.get("sha256") != digest(arrays):
                why = "checksum mismatch (corrupt)"
        if why is not None:
            warn(f"chunk file {path} is {why}: computing the chunk again")
            self.recomputed.append(index)
            return None
        return arrays


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
