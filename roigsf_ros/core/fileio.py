"""Atomic outputs: write under a temporary name beside the target, rename when complete; and the checked read.

A crash or a bad input half-way never leaves a partial file or folder under the final name; a JSON file that is
missing or cut short is an ``InputError`` naming it.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from roigsf_ros.core.errors import InputError


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


OUTPUT_MARKS = ("cam_params.json", "keyframes.json", "metadata.yaml", "metrics.json", "results.json")
"""Files that make a folder an output of this package's writers, or of rosbag2: a scene, a saved map, a bag, a map,
pool or demo run, a bench. Such a folder inside an earlier output is never deleted by replacing it."""


def check_replaceable(
    final: str | Path,
    marks: Sequence[str] = (),
    what: str = "",
    inputs: Sequence[str | Path | None] = (),
    own: Sequence[str] = (),
) -> None:
    """Refuse an output at ``final`` that would delete what it must not (InputError naming it).

    An input of the command (``inputs``: the scene, bag or mesh it reads; None: not given) at ``final`` or under it:
    ``roigsf bench --scene X --out X --overwrite`` deleted the scene it had just benchmarked. With ``marks``, an
    existing ``final`` that is neither an empty folder nor ``what``, an earlier output of the same kind (a real folder
    holding one of the files ``marks`` names): ``--overwrite`` on a mistyped ``--out`` deleted a folder of other
    things. And an earlier output holding another output (a folder with one of :data:`OUTPUT_MARKS` inside it, other
    than the command's ``own``, glob patterns relative to ``final`` such as a bench's ``runs/*/*``): a bag or a map
    run written into a scene folder went with the scene's ``--overwrite``.
    """
    path = Path(final)
    target = path.resolve()
    for item in inputs:
        if item is None or not Path(item).exists():  # nothing to lose (a frame source in memory names no file)
            continue
        read = Path(item).resolve()
        if read == target or target in read.parents:
            raise InputError(final, f"holds {item}, which this command reads: writing there would delete it (give "
                                    "another output path)")  # fmt: skip
    if not marks or not (path.exists() or path.is_symlink()):
        return
    real_dir = path.is_dir() and not path.is_symlink()
    if real_dir and not any(path.iterdir()):
        return
    if not (real_dir and any((path / m).is_file() for m in marks)):
        desc = f"a folder without {' or '.join(marks)}" if real_dir else "not a folder"
        raise InputError(final, f"is {desc}, not {what}: only {what} (or an empty folder) is replaced")
    nested = nested_output(path, own)
    if nested is not None:
        raise InputError(final, f"holds {nested}, an output of its own: replacing {what} would delete it (move it "
                                "out first, or give another output path)")  # fmt: skip


def nested_output(folder: Path, own: Sequence[str] = ()) -> str | None:
    """The first folder under ``folder`` (relative, with the file that marks it) that holds one of
    :data:`OUTPUT_MARKS`, other than those matching the ``own`` patterns; None if there is none.
    """
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames.sort()
        rel = Path(dirpath).relative_to(folder)
        if rel == Path("."):
            continue
        if any(fnmatch.fnmatch(rel.as_posix(), pattern) for pattern in own):
            dirnames.clear()  # the command's own output, and what it holds
            continue
        for mark in OUTPUT_MARKS:
            if mark in filenames:
                return f"{rel.as_posix()}/ ({mark})"
    return None


def check_replaceable_file(out: str | Path, mark: dict[str, Any], what: str) -> None:
    """Refuse a single-file output ``out`` that exists and is not ``what``, an earlier result of the same command (a
    JSON object holding every key of ``mark`` with its value, any value where None): ``roigsf perf io --out
    bags/x/metadata.yaml`` wrote its JSON over a bag's metadata. An earlier result is replaced (a re-run benchmark's).
    """
    path = Path(out)
    if not path.is_file():
        return
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        data = None
    if not (isinstance(data, dict) and all(k in data and (v is None or data[k] == v) for k, v in mark.items())):
        keys = ", ".join(f"{k}: {v!r}" if v is not None else k for k, v in mark.items())
        raise InputError(out, f"exists and is not {what} (a JSON object with {keys}): only such a file is replaced; "
                              "give another output path")  # fmt: skip


def check_run_output(
    out_dir: str | Path, overwrite: bool, what: str, inputs: Sequence[str | Path | None], marks: Sequence[str]
) -> dict[str, Any]:
    """Check a run's output folder before the run, not after its work: an existing one without ``overwrite`` is a
    FileExistsError, one holding an input or other things than ``what`` (``marks``) an InputError
    (:func:`check_replaceable`). Returns :func:`atomic_dir`'s keyword arguments that write it the same way.
    """
    out = Path(out_dir)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (overwrite=True replaces it)")
    keep: dict[str, Any] = {"marks": marks if overwrite else (), "what": what, "inputs": list(inputs)}
    check_replaceable(out, **keep)
    return keep


@contextlib.contextmanager
def atomic_dir(
    final: str | Path,
    overwrite: bool = False,
    overwrite_hint: str | None = None,
    marks: Sequence[str] = (),
    what: str = "",
    inputs: Sequence[str | Path | None] = (),
    own: Sequence[str] = (),
) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``final``; rename it to ``final`` on success.

    On an exception the temporary folder is removed and ``final`` is untouched. With
    ``overwrite`` an existing ``final`` (folder, file or symlink) is replaced only after the new one
    is complete, and removed: nothing but the new folder remains. Without it an existing ``final`` is a
    FileExistsError whose ``overwrite_hint`` tells how the caller's user asks to replace it: the command line's
    ``pass --overwrite`` by default, a request field for a service (``set overwrite: true in the request``).
    ``marks``, ``what``, ``inputs``, ``own``: what may be replaced and what never (:func:`check_replaceable`), checked
    first.
    """
    final = Path(final)
    check_output_name(final)
    check_replaceable(final, marks if overwrite else (), what, inputs, own)
    if final.exists() and not overwrite:
        hint = "pass --overwrite" if overwrite_hint is None else overwrite_hint
        raise FileExistsError(f"{final}: already exists ({hint} to replace it)")
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(final, final.name)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-{os.getpid()}-", dir=final.parent))
    tmp.chmod(0o777 & ~_umask())  # mkdtemp makes 0700; the result should look like any new folder
    try:
        yield tmp
        with deferred_interrupts():  # a Ctrl-C between the renames would leave neither folder at ``final``
            if final.exists() or final.is_symlink():
                old = final.with_name(f".{final.name}.old-{os.getpid()}")
                final.rename(old)
                try:
                    tmp.rename(final)
                except BaseException:
                    old.rename(final)  # the old output back where it was
                    raise
                _remove(old)
            else:
                tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def check_output_name(out: str | Path) -> None:
    """Refuse an output path that names no entry of its own: ``.``, ``..``, ``/``, ``x/..``, or the working folder
    or one above it (written beside and renamed, the output would replace the folder the process runs in).
    """
    path = Path(out)
    if path.name in ("", ".", ".."):
        raise InputError(out, "names no folder or file of its own (give a new name, e.g. runs/out)")
    resolved, cwd = Path(os.path.abspath(path)), Path.cwd()
    if resolved == cwd or resolved in cwd.parents:
        raise InputError(out, "is the working folder or one above it; give a new name inside it")


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then deliver them: for steps a Ctrl-C must not split.

    Such as swapping an old output for a new one (two renames). In a thread other than the main one (where Python runs
    no signal handler) and for a signal whose handler was not set from Python, the block runs as is.
    """
    held: list[int] = []
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not None:
                previous[sig] = signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(held):
            signal.raise_signal(sig)


def check_writable(out: str | Path, file: bool = False) -> None:
    """Fail before any work if ``out`` cannot be created: its parent is read-only, not writable or not a folder.

    Outputs are written beside their final name and renamed (:func:`atomic_dir`, :func:`atomic_path`), so the test
    is to create and remove a temporary file in the parent (or the nearest existing ancestor, as missing parents
    are created); a run would otherwise fail only at its end, and a path under a regular file with a bare
    ``[Errno 17] File exists``. The one check of the command line and of the mapper's ``~/save_map``. With ``file``
    (the caller writes one file, such as ``--out FILE.json``) an existing folder at ``out`` is refused too, as
    :func:`atomic_path` would refuse it only after the work.
    """
    check_output_name(out)
    if file and Path(out).is_dir():
        raise InputError(out, "is a folder; give a file name")
    folder = Path(os.path.abspath(out)).parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(folder, f"is not a folder, so the output {out} cannot be created there")
    try:
        fd, probe = tempfile.mkstemp(prefix=".roigsf-write-test-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        where = f"{out} cannot be written there" if Path(os.path.abspath(out)).parent != folder else ""
        why = f"output folder is not writable: the system refused a new file in it ({exc.strerror or exc})"
        raise InputError(folder, f"{why}{'; ' + where if where else ''}; choose another one") from None


def remove_stale_temporaries(final: str | Path, stem: str) -> list[Path]:
    """Remove the temporaries of ``final`` (``.STEM.tmp-PID-*`` beside it) whose writer process is gone.

    A process killed outright (SIGKILL, power loss) cannot clean up; its hidden temporary stays beside the output
    until the next write of that output, which removes it here. One whose process still runs is left alone, and
    so is the ``.NAME.old-PID`` of an interrupted replacement (it may be the only copy of the old output).
    """
    final = Path(final)
    prefix = f".{stem}.tmp-"
    removed = []
    try:
        entries = [e for e in final.parent.iterdir() if e.name.startswith(prefix)]
    except OSError:
        return removed
    for entry in entries:
        pid, sep, _ = entry.name[len(prefix) :].partition("-")
        if not (sep and pid.isdigit()) or _process_runs(int(pid)):
            continue
        _remove(entry)
        removed.append(entry)
    return removed


def _process_runs(pid: int) -> bool:
    """Whether a process with this id runs on this machine (one we may not signal runs too)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _remove(path: Path) -> None:
    """Delete what was replaced: a folder with its contents, or a file or symlink (never a link's target)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(final: str | Path) -> Iterator[Path]:
    """Yield a temporary file path beside ``final``; ``os.replace`` it onto ``final`` on success.

    The temporary file is removed whatever fails, the rename included; an existing folder at ``final`` (which the
    rename cannot replace) or a regular file where a parent folder should be is an ``InputError`` naming it, raised
    before the temporary file is made.
    """
    final = Path(final)
    check_output_name(final)
    if final.is_dir():
        raise InputError(final, "is a folder; give a file name")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = final.parent
        while not blocker.exists() and blocker != blocker.parent:
            blocker = blocker.parent
        raise InputError(blocker, f"is not a folder, so the output {final} cannot be created there") from None
    remove_stale_temporaries(final, final.stem)
    fd, name = tempfile.mkstemp(prefix=f".{final.stem}.tmp-{os.getpid()}-", suffix=final.suffix, dir=final.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        tmp.chmod(0o666 & ~_umask())  # mkstemp makes 0600
        yield tmp
        try:
            os.replace(tmp, final)
        except IsADirectoryError:  # a folder made there meanwhile
            raise InputError(final, "is a folder; give a file name") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_json(path: str | Path, missing: str = "not found") -> dict[str, Any]:
    """The JSON object in ``path``; InputError naming the file when it is absent (``missing`` says what to give
    instead), unreadable, not JSON (a write cut short) or not an object.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise InputError(path, missing) from None
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc}); was its writer interrupted?") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(path, f"not a JSON object (a {type(data).__name__})")
    return data


__all__ = [
    "OUTPUT_MARKS",
    "atomic_dir",
    "atomic_path",
    "check_output_name",
    "check_replaceable",
    "check_replaceable_file",
    "check_run_output",
    "check_writable",
    "deferred_interrupts",
    "nested_output",
    "read_json",
    "remove_stale_temporaries",
    "write_json",
]
