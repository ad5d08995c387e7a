"""Film output: linear float32 EXR, sRGB PNG preview, JSON sidecar (all written atomically).

Every file is first written to a hidden temp file in the destination directory
(`.NAME.tmp<pid>.XXXX`) and then moved over the destination with `os.replace`, so a process
killed at any moment leaves either the previous complete file or the new complete file,
never a truncated one. A temp file orphaned by a kill starts with a dot and does not end
in the real extension, so it cannot be mistaken for an output; it names the process that
made it, and `recover_outputs` (run at the start of the next render to the same output)
removes those whose process is gone.

The set OUT.exr + OUT.png + OUT.json (`write_outputs`) cannot be replaced in one atomic
step, so the EXR is the record: it is renamed first and carries the whole JSON record in
its header (attribute "jaxvcm"); the PNG follows and the JSON, which names the EXR's and
the PNG's SHA-256, comes last. A kill between the renames leaves a newer EXR beside an
older PNG / JSON; `check_outputs` sees that, and `recover_outputs` rewrites the PNG and
the JSON from the EXR, so the next start (or a reader who calls it) has a consistent set.
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import hashlib
import io
import json
import os
import re
import tempfile
import threading
from collections.abc import Iterator

import numpy as np

__all__ = ["read_exr", "write_outputs", "atomic_path", "write_exr", "write_png",
           "check_outputs", "recover_outputs", "OutputError"]

META_ATTR = "jaxvcm"  # the EXR header attribute holding the JSON record


class OutputError(OSError):
    """An output that cannot be written; str() is one line naming the user's path (never
    the temp file next to it)."""


def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def _tmp_prefix(path: str) -> str:
    return f".{os.path.basename(path)}.tmp"


def _mkstemp_near(path: str) -> str:
    d = os.path.dirname(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=d, prefix=f"{_tmp_prefix(path)}{os.getpid()}.")
    except OSError as e:
        raise OutputError(f"{path}: cannot write: {e.strerror or e}") from None
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual mode
    except (OSError, AttributeError):
        pass
    os.close(fd)
    return tmp


@contextlib.contextmanager
def _signals_held():
    """Defer SIGINT/SIGTERM (main thread) so a short critical section completes: Python-level
    handlers that only record the signal replace the current ones for the duration; on the
    way out the old handlers are restored and the first recorded signal is re-delivered to
    them (SIGINT: KeyboardInterrupt at the end of the section). No thread signal mask is
    touched: with a blocked mask a process-directed signal goes to one of XLA's threads,
    and a section that blocks it was seen to lose a Ctrl-C under heavy load."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {}
    try:
        for sig in sigs:
            old[sig] = signal.signal(sig, lambda n, _f: got.append(n))
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        if got:
            h = old.get(got[0])
            if callable(h):
                h(got[0], None)  # the default SIGINT handler raises KeyboardInterrupt
            elif h != signal.SIG_IGN:
                signal.raise_signal(got[0])  # SIG_DFL: the default action, now


@contextlib.contextmanager
def atomic_paths(paths: list[str]) -> Iterator[list[str]]:
    """Yield temp paths next to `paths`; on success move each over its destination, on
    any failure remove them all and leave the destinations untouched. SIGINT/SIGTERM are
    held back for the duration (a Ctrl-C lands right after the files are complete), so
    only SIGKILL can interrupt it, and that leaves at most hidden `.NAME.tmp*` files."""
    shown = [os.fspath(p) for p in paths]
    paths = [os.path.abspath(p) for p in shown]
    tmps: list[str] = []
    with _signals_held():
        try:
            for p in shown:
                tmps.append(_mkstemp_near(p))
            try:
                yield list(tmps)
            except OSError as e:
                if isinstance(e, OutputError):
                    raise
                raise OutputError(f"{shown[0]}: cannot write: {e.strerror or e}") from None
            for t in tmps:
                _fsync_file(t)
            for t, p, sp in zip(tmps, paths, shown):
                try:
                    os.replace(t, p)
                except OSError as e:
                    raise OutputError(f"{sp}: cannot write: {e.strerror or e}") from None
        except BaseException:
            for t in tmps:
                with contextlib.suppress(OSError):
                    os.unlink(t)
            raise


@contextlib.contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """Yield a temp path next to `path`; on success move it over `path`, on any failure
    (including KeyboardInterrupt) remove it and leave `path` untouched."""
    with atomic_paths([path]) as (tmp,):
        yield tmp


def check_writable(path: str) -> None:
    """Raise `OutputError` (one line naming `path`) now if `path` cannot be written the way
    the outputs are (a temp file beside it), rather than after a long render."""
    os.unlink(_mkstemp_near(os.fspath(path)))


def check_output_set(out_path: str) -> None:
    """Check, before any work, that the output set of `out_path` (.exr + .png + .json) can
    be written: a non-empty path ending in .exr, none of the three a directory, the folder
    writable (a temp file beside it), and no other render writing the set now
    (`output_lock`). Each failure is one line naming the path (`ValueError` for a malformed
    path, `OutputError` otherwise)."""
    if not str(out_path).strip():
        raise ValueError("out: empty; name an .exr file")
    paths = _set_paths(out_path)
    for p in paths:
        if os.path.isdir(p):
            raise OutputError(f"{p}: is a directory, not a file to write")
    d = os.path.dirname(os.path.abspath(paths[0]))
    up = d
    while up and not os.path.exists(up):
        up = os.path.dirname(up)
    if up and not os.path.isdir(up):
        raise OutputError(f"{out_path}: cannot write: {up} is not a directory")
    if os.path.isdir(d):
        check_writable(paths[0])
        with output_lock(paths[0]):
            pass


def _lock_path(out_path: str) -> str:
    d, name = os.path.split(os.path.abspath(os.fspath(out_path)))
    return os.path.join(d, f".{name}.lock")


def _remove_stale_lock(out_path: str) -> bool:
    """Remove the lock file of `out_path` if no process holds it (a killed render's); one
    that is held (by another render, or by this process's own `output_lock`: flock locks
    belong to open files, so a second open of it here cannot take it) stays."""
    lp = _lock_path(out_path)
    try:
        fd = os.open(lp, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    try:
        os.unlink(lp)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


@contextlib.contextmanager
def output_lock(out_path: str):
    """Hold the output set of `out_path` for one render: a second render (another process)
    to the same set is refused in one line (`OutputError`) instead of overwriting it. An
    advisory `flock` on a hidden lock file beside it: the system releases it when the
    holder exits or is killed, so a killed render never leaves the set locked (only the
    empty lock file, which the next render takes over and removes)."""
    lp = _lock_path(out_path)
    try:
        fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o666 & ~_UMASK)
    except OSError as e:
        raise OutputError(f"{out_path}: cannot write: {e.strerror or e}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise OutputError(f"{out_path}: another render is writing this output set "
                              f"now (it holds {lp})") from None
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                os.unlink(lp)
    finally:
        os.close(fd)


def _fsync_file(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _check_image(image) -> np.ndarray:
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1 or a.shape[2] < 1:
        raise ValueError(f"image: expected an array [H, W, C], got shape {np.shape(image)}")
    return a


def _channels(a: np.ndarray, layer: str = "") -> dict:
    C = a.shape[2]
    pre = layer + "." if layer else ""
    if C == 3 and not layer:
        return {"RGB": np.ascontiguousarray(a)}
    if C == 3:
        return {pre + k: np.ascontiguousarray(a[..., i]) for i, k in enumerate("RGB")}
    if C == 1:
        return {pre + "Y": np.ascontiguousarray(a[..., 0])}
    return {f"{pre}C{c}": np.ascontiguousarray(a[..., c]) for c in range(C)}


def _layered(a: np.ndarray, layers: dict | None) -> dict:
    """The image's channels, then each layer's as LAYER.R, LAYER.G, LAYER.B (EXR's layer
    convention), same shape as the image."""
    ch = _channels(a)
    for name, img in (layers or {}).items():
        la = _check_image(img)
        if la.shape != a.shape:
            raise ValueError(f"layers[{name!r}]: shape {la.shape}, the image's is {a.shape}")
        ch.update(_channels(la, name))
    return ch


def _exr_header(header: dict | None) -> dict:
    import OpenEXR

    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if header:
        hdr.update(header)
    return hdr


def write_exr(path: str, image, header: dict | None = None) -> None:
    """Write a linear float32 EXR atomically (RGB for 3 channels, Y for 1, C0.. otherwise)."""
    import OpenEXR

    a = _check_image(image)
    with atomic_path(path) as tmp:
        OpenEXR.File(_exr_header(header), _channels(a)).write(tmp)


def prefetch_imports() -> threading.Thread:
    """Import what writing the outputs needs (colour-science: about 2 s; matplotlib's PNG
    writer; OpenEXR) on a daemon thread, so that it overlaps the first pass, which spends
    its time in XLA with the GIL released, instead of following it."""
    def work():
        with contextlib.suppress(Exception):  # the writer imports again and reports
            import colour  # noqa: F401
            import matplotlib.image  # noqa: F401
            import OpenEXR  # noqa: F401

    t = threading.Thread(target=work, name="jaxvcm-prefetch-imports", daemon=True)
    t.start()
    return t


SRGB_STRIP = 1 << 20  # values per strip of `to_srgb8`


def to_srgb8(image, exposure: float = 0.0) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB preview (exposure in stops; NaN/Inf shown as 0/1),
    computed in strips of rows (about SRGB_STRIP values each), so that its float64
    temporaries do not scale with the image (a 16384^2 image would need some 40 GB)."""
    import colour

    img = _check_image(image)
    H, W, C = img.shape
    out = np.empty((H, W, C), np.uint8)
    step = max(1, SRGB_STRIP // (W * C))
    for y in range(0, H, step):  # in strips of rows: the float64 temporaries stay small
        a = img[y:y + step].astype(np.float64) * 2.0 ** float(exposure)
        a = np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0)
        a = np.clip(a, 0.0, 1.0)
        enc = np.asarray(colour.cctf_encoding(a, function="sRGB"), dtype=np.float64)
        out[y:y + step] = np.round(np.clip(enc, 0.0, 1.0) * 255.0).astype(np.uint8)
    if C == 1:
        out = np.repeat(out, 3, axis=2)
    elif C == 2:
        out = np.concatenate([out, np.zeros_like(out[..., :1])], axis=2)
    elif C > 3:
        out = out[..., :3]
    return out


def png_bytes(image, exposure: float = 0.0) -> bytes:
    """The sRGB 8-bit PNG preview of a linear image, encoded in memory."""
    import matplotlib.image as mpimg

    buf = io.BytesIO()
    mpimg.imsave(buf, to_srgb8(image, exposure), format="png")
    return buf.getvalue()


def write_png(path: str, image, exposure: float = 0.0) -> None:
    """Write the sRGB 8-bit preview of a linear image atomically."""
    data = png_bytes(image, exposure)
    with atomic_path(path) as tmp:
        _write_bytes(tmp, data)


def _json_text(meta: dict) -> str:
    return json.dumps(meta, indent=2, default=_json_default) + "\n"


def _write_bytes(path: str, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "__array__"):
        return np.asarray(o).tolist()
    return str(o)


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _set_paths(out_path: str) -> tuple[str, str, str]:
    out_path = os.fspath(out_path)
    stem, ext = os.path.splitext(out_path)
    if ext.lower() != ".exr":
        raise ValueError(f"out: must end in .exr, got {out_path!r}")
    return out_path, stem + ".png", stem + ".json"


def write_outputs(out_path: str, image, meta: dict, exposure: float = 0.0,
                  layers: dict | None = None) -> None:
    """Write `out_path` (.exr, linear float32; `layers` {name: image} as extra EXR layers
    beside the image's channels), the PNG preview (`.png`, image * 2**exposure,
    sRGB, 8-bit) and the JSON sidecar (`.json`, `meta` plus "exposure" and "files": the
    SHA-256 of the EXR and the PNG) next to it. The directory must exist.

    Everything is encoded and written to temp files first; the renames follow each other
    immediately (SIGINT/SIGTERM held back) in the order EXR, PNG, JSON. The EXR holds the
    record in its header, so even a SIGKILL between two renames leaves a set that
    `recover_outputs` makes consistent (the module's docstring)."""
    import OpenEXR

    p_exr, p_png, p_json = _set_paths(out_path)
    a = _check_image(image)
    png = png_bytes(a, exposure)
    meta = {**meta, "exposure": float(exposure)}
    with atomic_paths([p_exr, p_png, p_json]) as (t_exr, t_png, t_json):
        OpenEXR.File(_exr_header({META_ATTR: _json_text(meta)}), _layered(a, layers)).write(t_exr)
        _write_bytes(t_png, png)
        files = {"exr_sha256": _sha256(t_exr), "png_sha256": hashlib.sha256(png).hexdigest()}
        _write_bytes(t_json, _json_text({**meta, "files": files}).encode("utf-8"))


def check_outputs(out_path: str) -> list[str]:
    """What is wrong with the set `out_path` (.exr) + .png + .json: [] when all three exist,
    the JSON names the EXR's and the PNG's SHA-256 and agrees with the record in the EXR's
    header; otherwise one line per problem."""
    p_exr, p_png, p_json = _set_paths(out_path)
    missing = [p for p in (p_exr, p_png, p_json) if not os.path.isfile(p)]
    if missing:
        return [f"{p}: missing" for p in missing]
    try:
        with open(p_json, encoding="utf-8") as f:
            meta = json.load(f)
        files = meta.pop("files")
    except (OSError, ValueError, KeyError, AttributeError) as e:
        return [f"{p_json}: not a jaxvcm record ({e})"]
    problems = []
    if files.get("exr_sha256") != _sha256(p_exr):
        problems.append(f"{p_exr}: not the EXR that {p_json} describes")
    if files.get("png_sha256") != _sha256(p_png):
        problems.append(f"{p_png}: not the PNG that {p_json} describes")
    if not problems and _exr_record(p_exr) != meta:
        problems.append(f"{p_json}: differs from the record in {p_exr}")
    return problems


def _exr_record(path: str) -> dict | None:
    import OpenEXR

    try:
        text = OpenEXR.File(path).header().get(META_ATTR)
        return json.loads(text) if isinstance(text, str) else None
    except Exception:  # noqa: BLE001 (an unreadable or foreign EXR: no record)
        return None


def read_record(path: str) -> dict | None:
    """The JSON record a jaxvcm EXR carries in its header (None: no such EXR or no
    record)."""
    return _exr_record(path) if os.path.isfile(path) else None


def _stale_temps(path: str) -> list[str]:
    """Temp files next to `path` made by processes that no longer run."""
    pre = _tmp_prefix(path)
    stale = []
    for t in glob.glob(os.path.join(glob.escape(os.path.dirname(path) or "."),
                                    glob.escape(pre) + "*")):
        m = re.fullmatch(r"(\d+)\..*", os.path.basename(t)[len(pre):])
        if m is None:
            continue
        pid = int(m.group(1))
        if pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            stale.append(t)
        except (PermissionError, OverflowError, ValueError):
            pass  # alive (another user's) or not a pid
    return stale


def recover_outputs(out_path: str) -> list[str]:
    """Make the set at `out_path` consistent after a killed writer, and tidy up: remove the
    temp files and the lock file (`output_lock`) of dead processes, and if the PNG or JSON is not the one for the EXR (a kill
    between the renames), rewrite both from the record in the EXR's header. Returns what
    was done, one line each (empty when nothing was needed)."""
    p_exr, p_png, p_json = _set_paths(out_path)
    done = []
    for p in (p_exr, p_png, p_json):
        for t in _stale_temps(os.path.abspath(p)):
            with contextlib.suppress(OSError):
                os.unlink(t)
                done.append(f"removed {t}")
    if _remove_stale_lock(p_exr):
        done.append(f"removed {_lock_path(p_exr)}")
    if os.path.isfile(p_exr) and check_outputs(p_exr):
        meta = _exr_record(p_exr)
        if meta is not None:
            a = read_exr(p_exr)
            png = png_bytes(a, meta.get("exposure", 0.0))
            with atomic_paths([p_png, p_json]) as (t_png, t_json):
                _write_bytes(t_png, png)
                files = {"exr_sha256": _sha256(p_exr),
                         "png_sha256": hashlib.sha256(png).hexdigest()}
                _write_bytes(t_json, _json_text({**meta, "files": files}).encode("utf-8"))
            done.append(f"rewrote {p_png} and {p_json} from {p_exr}")
    return done


def read_exr(path: str) -> np.ndarray:
    """Read an EXR written by `write_exr` (or any RGB EXR) as float32 [H, W, 3]."""
    import OpenEXR

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: file not found")
    f = OpenEXR.File(path, separate_channels=True)
    ch = f.channels()
    if all(k in ch for k in "RGB"):
        planes = [ch[k].pixels for k in "RGB"]
    elif "Y" in ch:
        planes = [ch["Y"].pixels] * 3
    else:
        raise ValueError(f"{path}: no R, G, B or Y channels (found: {', '.join(sorted(ch))})")
    return np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1)


def read_exr_layers(path: str) -> dict[str, np.ndarray]:
    """The layers of an EXR written with `write_outputs(layers=...)` (channels LAYER.R,
    LAYER.G, LAYER.B, or LAYER.Y), as {LAYER: float32 [H, W, 3]}, in file order; the image
    itself is `read_exr`."""
    import OpenEXR

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: file not found")
    ch = OpenEXR.File(path, separate_channels=True).channels()
    names: dict[str, None] = {}
    for k in ch:
        if "." in k:
            names[k.rsplit(".", 1)[0]] = None
    out = {}
    for name in names:
        if all(f"{name}.{c}" in ch for c in "RGB"):
            planes = [ch[f"{name}.{c}"].pixels for c in "RGB"]
        elif f"{name}.Y" in ch:
            planes = [ch[f"{name}.Y"].pixels] * 3
        else:
            continue
        out[name] = np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1)
    return out
