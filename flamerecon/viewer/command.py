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

import signal
import socket
import sys
import threading

from flamerecon.run.cli import at_least, run_script, script_parser


def ssh_hint(port: int) -> str:
    """How to reach a viewer on a remote machine from one's own."""
    user_host = f"USER@{socket.gethostname() or 'HOST'}"
    return (f"on another machine: ssh -N -L {port}:localhost:{port} {user_host}, "
            f"then open http://localhost:{port} there")


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
    parser.add_argument("--port", type=at_least(1), default=8080, help="port to serve on (default 8080; "
                        "the next free one if taken)")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1, this "
                        "machine only: reach it from elsewhere by SSH port forwarding; 0.0.0.0 for every network)")
    parser.add_argument("--device", default="auto", help="where renders run: auto (CUDA when present), cpu, cuda")
    args = parser.parse_args(argv)
    stop = threading.Event()

    def body() -> int:
        from flamerecon.viewer.server import Viewer

        previous = {sig: signal.signal(sig, lambda *_: stop.set())
                    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        try:
            print(f"flamerecon view: loading {args.run_dir} ...", flush=True)
            viewer = Viewer(args.run_dir, args.host, args.port, args.device)
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
