"""``flamerecon view RUN_DIR``: look at a reconstruction in the browser.

    flamerecon view outputs/DATE/TIME             # a run folder
    flamerecon view multirun/DATE/TIME            # a multirun of frames (assembled or not): a time slider
    flamerecon view RUN_DIR --port 8080 --host 127.0.0.1 --device auto

Prints the address to open and, for a remote machine, the SSH port forward that reaches it;
serves until Ctrl-C (or SIGTERM / SIGHUP), then stops cleanly with exit status 0. The density is
rendered by flamerecon for the browser's own camera, beside the capture's cameras with their
images (held-out ones red, with their scores), the iso-surface and slices with a colour bar
(toggles), an exposure control and, for a sequence, a time slider. Needs
``pip install 'flamerecon[view]'``.
"""

from __future__ import annotations

import argparse
import signal
import socket
import sys
import threading

from flamerecon.interrupt import STOP_SIGNALS
from flamerecon.run.cli import run_script, script_parser


def ssh_hint(port: int) -> str:
    """How to reach a viewer on a remote machine from one's own."""
    user_host = f"USER@{socket.gethostname() or 'HOST'}"
    return (f"on another machine: ssh -N -L {port}:localhost:{port} {user_host}, "
            f"then open http://localhost:{port} there")


def port_number(text: str) -> int:
    """argparse type of ``--port``: a whole number from 1 to 65535."""
    from flamerecon.viewer.address import MAX_PORT

    try:
        number = int(text)
    except ValueError:
        number = 0
    if not 1 <= number <= MAX_PORT:
        raise argparse.ArgumentTypeError(f"got '{text}'; a port is a whole number from 1 to {MAX_PORT}")
    return number


def serve(viewer, stop: threading.Event) -> None:
    """Wait for ``stop`` (set by Ctrl-C, SIGTERM or SIGHUP) and close the viewer."""
    try:
        while not stop.wait(0.2):
            pass
    finally:
        viewer.stop()


def main(argv: list[str] | None = None) -> int:
    parser = script_parser(__doc__, "flamerecon view")
    parser.add_argument("run_dir", help="a run folder (density.npz, .hydra/) or a multirun folder of them")
    parser.add_argument("--port", type=port_number, default=8080, help="port to serve on, 1-65535 (default "
                        "8080; the next free one if taken)")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1, this "
                        "machine only: reach it from elsewhere by SSH port forwarding; 0.0.0.0 for every network)")
    parser.add_argument("--device", default="auto", help="where renders run: auto (CUDA when present), cpu, cuda")
    args = parser.parse_args(argv)
    stop = threading.Event()

    def body() -> int:
        from flamerecon.viewer.address import listen_address
        from flamerecon.viewer.server import Viewer

        listen_address(args.host, args.port)  # a bad --host or --port before anything is loaded
        print(f"flamerecon view: loading {args.run_dir} ...", flush=True)
        # until it serves, a stop signal ends the command as in every script (one line, 130)
        viewer = Viewer(args.run_dir, args.host, args.port, args.device)
        previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in STOP_SIGNALS}
        try:
            print(f"flamerecon view: open {viewer.url} in a browser ({len(viewer.frames)} frame(s))\n"
                  f"  {ssh_hint(viewer.port)}\n  Ctrl-C stops it", flush=True)
            serve(viewer, stop)
            print("flamerecon view: stopped", flush=True)
            return 0
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    return run_script(body, args.debug)


if __name__ == "__main__":
    sys.exit(main())
