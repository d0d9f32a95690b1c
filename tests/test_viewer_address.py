"""A viewer that cannot listen says so in one line and never hangs (issue 38, family 1).

viser binds in a thread of its own and waited for ever when that thread failed (a port past
65535, a host that does not resolve or is not this machine's), with the stop signals set to
nothing but a flag: the process then ignored SIGINT, SIGTERM and SIGHUP. Three tables: command
lines of ``flamerecon view`` (``python -m flamerecon`` and the installed command), calls of
``fr.view``, and real stop signals sent while viser starts (a stand-in viser that hangs or whose
server thread dies, on PYTHONPATH in front of the real one) and while it serves. Then a frame of a
viewed multirun that breaks: one line, once."""

from __future__ import annotations

import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from contextlib import contextmanager, nullcontext
from importlib.util import find_spec
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import flamerecon as fr
from flamerecon.errors import ArgumentError, ConfigError
from flamerecon.run.pipeline import reconstruct
from flamerecon.viewer.address import listen_address, start_viser
from tests.helpers import FAST, REPO, TINY, repo_env

needs_viser = pytest.mark.skipif(find_spec("viser") is None,
                                 reason="the viewer needs viser: pip install 'flamerecon[view]'")
#: an address no machine has (TEST-NET-1, RFC 5737)
NOT_HERE = "192.0.2.1"
NOWHERE = "no-such-host.invalid"  # .invalid never resolves (RFC 2606)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("view") / "run"
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[*TINY, *FAST])
    reconstruct(cfg, run)
    (run / ".hydra").mkdir()
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    return run


@contextmanager
def taken(port: int, host: str = "127.0.0.1"):
    """``port`` held by a listening socket for the block."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(1)
        yield


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def installed_command() -> str | None:
    return shutil.which("flamerecon", path=str(Path(sys.executable).parent))


ENTRIES = {"python -m flamerecon": lambda: [sys.executable, "-m", "flamerecon"],
           "flamerecon (installed)": lambda: [installed_command()]}

# (arguments after RUN, a port to hold while it runs (None: none), exit status, the one line)
COMMANDS = {
    "port past 65535": (["--port", "70000"], None, 2, r"--port: got '70000'; a port is a whole number from 1 to 65535"),
    "port 0": (["--port", "0"], None, 2, r"--port: got '0'; a port is a whole number from 1 to 65535"),
    "negative port": (["--port=-8080"], None, 2, r"--port: got '-8080'"),
    "port not a number": (["--port", "http"], None, 2, r"--port: got 'http'"),
    "65535 taken (it moved to 65536)": (["--port", "65535"], 65535, 2,
                                        r"--port: every port from 65535 to 65535 is taken on 127\.0\.0\.1"),
    "a host that does not resolve": (["--host", NOWHERE], None, 2,
                                     rf"--host: '{re.escape(NOWHERE)}' does not resolve"),
    "a host that is not this machine": (["--host", NOT_HERE], None, 2,
                                        rf"--host: '{NOT_HERE}' \({NOT_HERE}\) is not an address of this machine"),
    "a host and a port both bad": (["--host", NOWHERE, "--port", "99999"], None, 2, r"--port: got '99999'"),
}


@needs_viser
@pytest.mark.e2e
@pytest.mark.parametrize("entry", list(ENTRIES))
@pytest.mark.parametrize("case", list(COMMANDS))
def test_a_viewer_that_cannot_listen_says_so_in_one_line(case, entry, run_folder):
    if entry.startswith("flamerecon (") and installed_command() is None:
        pytest.skip("no installed flamerecon command beside this Python (pip install -e .)")
    args, hold, status, line = COMMANDS[case]
    command = [*ENTRIES[entry](), "view", str(run_folder), *args, "--device", "cpu"]
    with taken(hold) if hold else nullcontext():
        proc = subprocess.run(command, capture_output=True, text=True, env=repo_env(), cwd=REPO, timeout=120,
                              check=False)
    assert proc.returncode == status, proc.stdout + proc.stderr
    errors = [x for x in proc.stderr.splitlines() if x.strip()]
    assert len(errors) == 1 and errors[0].startswith("flamerecon: error: "), proc.stderr
    assert re.search(line, errors[0]), errors[0]
    assert "loading" not in proc.stdout  # refused before the run was loaded


# (keyword arguments of fr.view besides the run, a port to hold, the error, its message)
CALLS = {
    "port past 65535": ({"port": 70000}, None, ArgumentError, r"view\.port: got 70000"),
    "port 0": ({"port": 0}, None, ArgumentError, r"view\.port: got 0"),
    "65535 taken": ({"port": 65535}, 65535, ConfigError, r"view\.port: every port from 65535 to 65535 is taken"),
    "a host that does not resolve": ({"host": NOWHERE}, None, ConfigError, r"view\.host: .* does not resolve"),
    "a host that is not this machine": ({"host": NOT_HERE}, None, ConfigError,
                                        r"view\.host: .* is not an address of this machine"),
}


@needs_viser
@pytest.mark.parametrize("case", list(CALLS))
def test_fr_view_refuses_an_address_it_cannot_listen_on(case, run_folder):
    kwargs, hold, error, message = CALLS[case]
    with taken(hold) if hold else nullcontext(), pytest.raises(error, match=message):
        fr.view(run_folder, device="cpu", **kwargs)


def test_a_taken_port_moves_to_the_next_free_one():
    port = free_port()
    with taken(port):
        assert listen_address("127.0.0.1", port) > port
    assert listen_address("0.0.0.0", port) == port  # a wildcard is every address of this machine


@needs_viser
def test_a_bind_that_fails_in_visers_thread_is_one_error_not_a_wait():
    """The race the checks cannot close (the port taken between the check and viser's bind):
    viser's thread moves past 65535 and dies; the start says so instead of waiting for ever."""
    import viser

    with taken(65535), pytest.raises(ConfigError, match=r"viser could not listen on 127\.0\.0\.1:65535 "
                                                        r"\(OverflowError: bind\(\): port must be 0-65535"):
        start_viser(viser, "127.0.0.1", 65535)


# ---------------------------------------------------------------------------------------------
# real stop signals while viser starts (a stand-in viser) and while it serves (the real one)

STAND_INS = {
    "hangs": """
        import threading
        class ViserServer:
            def __init__(self, host, port, label=None, verbose=True):
                threading.Event().wait()  # its server thread never says it listens
    """,
    "thread dies": """
        import threading
        class ViserServer:
            def __init__(self, host, port, label=None, verbose=True):
                ready = threading.Semaphore(0)
                def bind():
                    raise OverflowError("bind(): port must be 0-65535.")
                threading.Thread(target=bind, daemon=True).start()
                ready.acquire()  # as viser waits: for ever
    """,
}


def start_view(run_folder: Path, port: int, stand_in: Path | None = None) -> subprocess.Popen:
    env = repo_env()
    if stand_in is not None:
        env["PYTHONPATH"] = f"{stand_in}:{env['PYTHONPATH']}"
    return subprocess.Popen([sys.executable, "-m", "flamerecon", "view", str(run_folder), "--port", str(port),
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=REPO)


def stand_in_viser(folder: Path, kind: str) -> Path:
    (folder / "viser").mkdir(parents=True)
    (folder / "viser" / "__init__.py").write_text(textwrap.dedent(STAND_INS[kind]))
    return folder


def read_until(proc: subprocess.Popen, text: str) -> str:
    lines = []
    while not any(text in line for line in lines):
        line = proc.stdout.readline()
        assert line, f"ended before '{text}': {''.join(lines)} {proc.stderr.read()[-2000:]}"
        lines.append(line)
    return "".join(lines)


# (stand-in viser or None for the real one, the signal, exit status, the one stderr line or None)
SIGNALS = {
    "SIGINT while viser hangs": ("hangs", "SIGINT", 130, r"interrupted by SIGINT"),
    "SIGTERM while viser hangs": ("hangs", "SIGTERM", 130, r"interrupted by SIGTERM"),
    "SIGHUP while viser hangs": ("hangs", "SIGHUP", 130, r"interrupted by SIGHUP"),
    "viser's thread dies (no signal)": ("thread dies", None, 2,
                                        r"viser could not listen on 127\.0\.0\.1:\d+ \(OverflowError"),
    "SIGTERM while serving": (None, "SIGTERM", 0, None),
    "SIGHUP while serving": (None, "SIGHUP", 0, None),
}


@needs_viser
@pytest.mark.e2e
@pytest.mark.parametrize("case", list(SIGNALS))
def test_stop_signals_are_acted_on_while_viser_starts_and_serves(case, run_folder, tmp_path):
    kind, sig, status, line = SIGNALS[case]
    proc = start_view(run_folder, free_port(), stand_in_viser(tmp_path, kind) if kind else None)
    try:
        read_until(proc, "Ctrl-C stops it" if kind is None else "loading")
        if sig is not None:
            time.sleep(1.0)  # inside viser's start (or its serving loop) by now
            proc.send_signal(getattr(signal, sig))
        out, err = proc.communicate(timeout=60)  # a process that ignored the signal fails here
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == status, out + err
    errors = [x for x in err.splitlines() if x.strip()]
    if line is None:
        assert "flamerecon view: stopped" in out and not errors, out + err
    else:
        assert len(errors) == 1 and re.search(line, errors[0]), err


# ---------------------------------------------------------------------------------------------
# a frame of a viewed multirun that breaks while viewed


@needs_viser
def test_a_frame_that_breaks_while_viewed_is_said_once(run_folder, tmp_path):
    from flamerecon.viewer.server import Viewer

    for job, frame in (("0", 3), ("1", 7)):
        shutil.copytree(run_folder, tmp_path / job)
        config = OmegaConf.load(tmp_path / job / ".hydra" / "config.yaml")
        config.scene.frame = frame
        OmegaConf.save(config, tmp_path / job / ".hydra" / "config.yaml")
    said: list[str] = []
    viewer = Viewer(tmp_path, port=free_port(), device="cpu", log=said.append)
    try:
        (tmp_path / "1" / "density.npz").write_bytes(b"not a density any more")  # broken while viewed
        for _ in range(5):  # five steps of the time slider onto it
            viewer._show_frame(1)
        assert len(said) == 1 and said[0].startswith("flamerecon view: frame 7 cannot be shown: "), said
        assert viewer.frame.label == "frame 3" and "still showing frame 3" in viewer.status.content
        viewer._show_frame(0)  # the frames that load still show
        assert viewer.frame.label == "frame 3"
    finally:
        viewer.stop()
