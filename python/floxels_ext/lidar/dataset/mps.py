"""CUDA MPS for ``floxels run``'s engines (``--mps``): the engine processes that share one GPU
become clients of one MPS server, so that their kernels run side by side instead of taking
turns.

Why: without MPS each engine process has its own CUDA context, and a GPU runs one context's
kernels at a time (time slices). ``accurate``'s ~500 small kernels a frame (the refinement, the
sights, the evidence) fill a few SMs each, so while one engine's small kernel runs the rest of
the GPU waits for the next time slice. Through one MPS server the engines' kernels share the SMs:
H100s, 16 cores, four engines, 768 frames, MPS and plain runs interleaved (medians of 8 and 6
runs): ``accurate`` KITTI layout 84.7 -> 102.7 frames/s, AV2 layout 114.3 -> 126.9; ``paper``
254.7 -> 278.6 and 248.6 -> 253.7 (bench/RESULTS.md, "The engines through CUDA MPS"). The
arithmetic is each kernel's own: the outputs are the same arrays with and without it.

``auto`` (the default) starts a *private* MPS control daemon for the run (its pipe and log in a
temporary directory; nothing system-wide is touched) when several engines share a CUDA device,
the daemon's program is on the PATH, and no MPS is set up already (``CUDA_MPS_PIPE_DIRECTORY``
set, or a daemon in the default ``/tmp/nvidia-mps``: the user's own, which this process and its
engines then use as they are). It is started before this process touches CUDA (so that engine 0,
the run's own process, is a client too) and tested with a CUDA client of its own (the driver API
through ctypes, in a subprocess); anything that fails leaves the run without MPS, with a note
(``auto``) or as an error (``on``).
A watcher process stops the daemon once the run's process has exited, however it exits, and
removes its directory. With ``--ray``, the workers are Ray's processes: start MPS on each node
before ``ray start`` (README, "Several GPUs and machines")."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile

__all__ = ["CONTROL", "MpsError", "mps_plan", "start_private_mps", "sharing", "use_mps"]

CONTROL = "nvidia-cuda-mps-control"
PIPE, LOG = "CUDA_MPS_PIPE_DIRECTORY", "CUDA_MPS_LOG_DIRECTORY"
DEFAULT_PIPE = "/tmp/nvidia-mps"  # where a daemon started without CUDA_MPS_PIPE_DIRECTORY listens (the
                                  # driver's default: CUDA processes without the variable join it)

# A CUDA client of its own, in a subprocess (the daemon starts its server for the first client):
# the driver API through ctypes, no torch import (~0.2 s). Exit 0: a context was made.
_PROBE = """
import ctypes, sys
try:
    cu = ctypes.CDLL("libcuda.so.1")
except OSError:
    sys.exit(3)
n, d, ctx = ctypes.c_int(), ctypes.c_int(), ctypes.c_void_p()
if cu.cuInit(0) != 0 or cu.cuDeviceGetCount(ctypes.byref(n)) != 0 or n.value < 1:
    sys.exit(4)
if cu.cuDeviceGet(ctypes.byref(d), 0) != 0:
    sys.exit(5)
sys.exit(6 if cu.cuDevicePrimaryCtxRetain(ctypes.byref(ctx), d) != 0 else 0)
"""
PROBE_ARGS = [sys.executable, "-c", _PROBE]  # (tests replace it: no GPU there)
NO_CUDA = {3, 4}  # the probe's exits for "no CUDA driver or no device": no note, MPS is moot

# Stops the daemon after the run's process ($1) has exited (normally, by an error, by a signal),
# then removes the directory ($3) of its pipe and log. In its own session: Ctrl-C in the
# terminal does not reach it.
_WATCH = 'while kill -0 "$1" 2>/dev/null; do sleep 1; done; echo quit | "$2" >/dev/null 2>&1; sleep 1; rm -rf "$3"'

_state: dict = {"sharing": None}  # this process: "private" (started here), "user" (already set up) or None


def _set_up(env) -> str | None:
    """Where an MPS set up before the run listens (``CUDA_MPS_PIPE_DIRECTORY``, else a daemon in
    the driver's default place), or None."""
    if env.get(PIPE):
        return f"{PIPE}={env[PIPE]}"
    if os.path.exists(os.path.join(DEFAULT_PIPE, "control")):
        return f"a daemon in {DEFAULT_PIPE}"
    return None


class MpsError(RuntimeError):
    """The private MPS daemon could not be started or did not serve a CUDA client."""


def mps_plan(mode: str, device: str | None, engines: int, ray: bool, environ=None,
             cuda_initialized: bool = False) -> tuple[str, str]:
    """What ``--mps MODE`` does for a run: ("start", why), ("user", why): the user's MPS is
    already set up, or ("none", why). Raises ``ValueError`` (the CLI's error) where ``on``
    cannot apply. ``device``: ``--device`` (None: CUDA if there is one); ``engines``: how many
    share it."""
    env = os.environ if environ is None else environ
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"--mps must be auto, on or off, got {mode!r}")
    if mode == "off":
        return "none", "--mps off"
    on = mode == "on"
    if device is not None and not device.startswith("cuda"):
        if on:
            raise ValueError(f"--mps on shares a GPU between engines; it contradicts --device {device}")
        return "none", "not on a GPU"
    if ray:
        if on:
            raise ValueError("--mps on starts MPS for this machine's engines; with --ray the workers are Ray's: "
                             "start MPS on each node before 'ray start' (README, 'Several GPUs and machines')")
        return "none", "Ray's workers"
    if engines < 2:
        if on:
            raise ValueError("--mps on shares a GPU between engines; this run has one (--engines 1 or "
                             "--worker-kind process)")
        return "none", "one engine"
    theirs = _set_up(env)
    if theirs:
        return "user", f"MPS already set up ({theirs})"
    if shutil.which(CONTROL) is None:
        if on:
            raise ValueError(f"--mps on: {CONTROL} is not on the PATH (it comes with the NVIDIA driver)")
        return "none", f"{CONTROL} not found"
    if cuda_initialized and not on:
        # this process's context is made already, outside MPS: its engines would take turns with it anyway
        return "none", "CUDA already in use by this process"
    return "start", "engines share a GPU"


def start_private_mps(timeout: float = 30.0) -> str:
    """Starts a private MPS control daemon, tests it with a CUDA client and points this process
    (and every process it starts from now on) at it; returns its directory. Raises
    :class:`MpsError` (the daemon stopped again) when it cannot serve."""
    root = tempfile.mkdtemp(prefix="floxels-mps-")
    env = dict(os.environ, **{PIPE: os.path.join(root, "pipe"), LOG: os.path.join(root, "log")})
    os.makedirs(env[PIPE])
    os.makedirs(env[LOG])
    control = shutil.which(CONTROL) or CONTROL
    try:
        r = subprocess.run([control, "-d"], env=env, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as e:
        shutil.rmtree(root, ignore_errors=True)
        raise MpsError(f"{CONTROL} -d: {e}") from None
    if r.returncode != 0:
        shutil.rmtree(root, ignore_errors=True)
        raise MpsError(f"{CONTROL} -d exited {r.returncode}: {(r.stderr or r.stdout).strip()[:200]}")
    # from here the daemon runs: the watcher stops it when this process ends, whatever happens next
    subprocess.Popen(["sh", "-c", _WATCH, "floxels-mps-watch", str(os.getpid()), control, root], env=env,
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                     start_new_session=True)
    try:
        probe = subprocess.run(PROBE_ARGS, env=env, capture_output=True, timeout=timeout).returncode
    except subprocess.TimeoutExpired:
        probe = "no answer in %.0f s" % timeout
    except OSError as e:
        probe = str(e)
    servers = ""
    if probe == 0:
        try:
            servers = subprocess.run([control], input="get_server_list\n", env=env, capture_output=True, text=True,
                                     timeout=timeout).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):
            servers = ""
    if probe != 0 or not servers:
        _quit(control, env)
        why = (f"a CUDA client: {probe}" if isinstance(probe, str) else f"a CUDA client exited {probe}" if probe
               else "no MPS server started for a CUDA client")
        raise MpsError(why, probe)
    os.environ[PIPE], os.environ[LOG] = env[PIPE], env[LOG]
    _state.update(sharing="private", pipe=env[PIPE])
    return root


def _quit(control: str, env: dict) -> None:
    try:
        subprocess.run([control], input="quit\n", env=env, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        pass  # the watcher tries again when the run ends


def use_mps(mode: str, device: str | None, engines: int, ray: bool) -> None:
    """``floxels run --mps MODE``, before the run touches CUDA: starts the private daemon where
    :func:`mps_plan` says so. ``auto``: a failure is a note on stderr and the run goes on
    without MPS; ``on``: a ``CLIError``."""
    from floxels_ext.errors import CLIError

    initialized = False
    if "torch" in sys.modules:
        initialized = sys.modules["torch"].cuda.is_initialized()
    try:
        what, _ = mps_plan(mode, device, engines, ray, cuda_initialized=initialized)
    except ValueError as e:
        raise CLIError(str(e)) from None
    if what != "start":
        # a later run of this process keeps the daemon an earlier one started ("private"); an MPS
        # set up before the run serves its engines whatever --mps says (sharing() finds it, "off" too)
        mine = _state["sharing"] == "private" and os.environ.get(PIPE) == _state.get("pipe")
        if what == "user" and not mine:
            _state["sharing"] = "user"
        return
    try:
        start_private_mps()
    except MpsError as e:
        code = e.args[1] if len(e.args) > 1 else None
        if mode == "on":
            raise CLIError(f"--mps on: CUDA MPS did not start ({e.args[0]})") from None
        if code not in NO_CUDA:
            print(f"floxels: note: CUDA MPS did not start ({e.args[0]}); the engines take turns on the GPU "
                  f"(--mps off skips the attempt)", file=sys.stderr)


def sharing() -> str:
    """Whether this process (and the engines it starts) use MPS: "private" (a daemon started by
    ``--mps``), "user" (one set up before the run: also what a Ray worker finds, which runs no
    ``--mps`` of its own) or "off"."""
    if _state["sharing"] is None and _set_up(os.environ):
        return "user"
    return _state["sharing"] or "off"
