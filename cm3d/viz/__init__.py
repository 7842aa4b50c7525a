"""Rerun recordings of a run (``cm3d run/demo --rerun PATH``, ``cm3d view PATH``).

The only package of cm3d that imports ``rerun`` (the optional ``viz`` extra: ``pip install -e '.[viz]'``),
and nothing in the core imports this package: the CLI and the demo import it when ``--rerun`` is given.
:mod:`.log` holds the logging primitives (one archetype each), :mod:`.record` the recorders of a
sequence, a multi-visit demo and a stitched long video, :mod:`.view` opening a recording.
"""

from __future__ import annotations


class RerunMissing(ValueError):
    """rerun-sdk is not installed (a ValueError: the CLI prints it as one line and exits 2)."""


def require_rerun():
    """The ``rerun`` module, or :class:`RerunMissing` saying how to install it."""
    try:
        import rerun
    except ImportError as err:
        raise RerunMissing(f"--rerun / view: needs the optional rerun-sdk package (pip install -e '.[viz]'): "
                           f"{err}") from None
    return rerun


def viewer_executable() -> str | None:
    """The ``rerun`` viewer that rerun-sdk installs (beside this Python, else on ``PATH``), or None."""
    import shutil
    import sys
    from pathlib import Path

    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else shutil.which("rerun")


def view(path, has_display: bool | None = None) -> str:
    """Open a recording in the rerun viewer when one is installed and a display exists (started in
    the background; returns at once), else say how to open it. Returns the line to print."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"view: no recording at {path}")
    exe = viewer_executable()
    if has_display is None:
        has_display = sys.platform in ("darwin", "win32") or bool(os.environ.get("DISPLAY") or
                                                                 os.environ.get("WAYLAND_DISPLAY"))
    how = (f"open it with `rerun {path}` on a machine with a display (pip install rerun-sdk), or serve the web "
           f"viewer from here: `rerun --web-viewer {path}` (then http://localhost:9090 in a browser)")
    if exe is None:
        return f"{path}: no rerun viewer installed; {how}"
    if not has_display:
        return f"{path}: no display here; {how}"
    subprocess.Popen([exe, str(path)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)
    return f"opened {path} in the rerun viewer ({exe})"


def check_recording_path(path):
    """Fail early (one-line ``ValueError``) when rerun-sdk is missing or ``path`` cannot be written."""
    from pathlib import Path

    from cm3d.data.atomic import check_writable_folder

    require_rerun()
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"--rerun {path}: is a folder, not a file")
    check_writable_folder(path.parent, f"--rerun {path}: its folder")
    return path
