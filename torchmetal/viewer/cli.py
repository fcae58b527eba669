"""``torchmetal view MATERIAL``: relight a material live in the browser (served from 127.0.0.1).

Only argparse at the top: the server, onnxruntime and torch load inside the verb.
"""

from __future__ import annotations

import argparse


def cmd_view(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C, then end the process (exit status 0); a bad argument raises before serving (the CLI's
    one-line error, exit 2)."""
    import os
    import signal
    import sys

    # on use: a verb module imports only argparse at the top (CLI start-up)
    from torchmetal.viewer.server import make_server

    def log(text: str) -> None:
        print(f"torchmetal view: {text}", file=sys.stderr, flush=True)

    server = make_server(args.material, capture=args.capture, port=args.port, threads=args.threads, log=log)
    cfg = server.viewer.config
    flakes = "flakes on/off" if "flakes" in cfg["graphs"] else "no flakes"
    print(f"viewing {args.material} ({cfg['height']}x{cfg['width']}, {flakes}, {len(cfg['shots'])} shots) at {server.url} "
          "(Ctrl-C stops)", flush=True)
    if not args.no_open:
        import webbrowser

        webbrowser.open(server.url)
    # Ctrl-C stops it even when started with SIGINT ignored (a background job of a non-interactive shell: Python
    # then keeps SIG_IGN and never raises KeyboardInterrupt, and the server ran on after Ctrl-C)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    finally:
        server.close()
    # Served until Ctrl-C: end the process here (its request threads are daemons and onnxruntime's thread pools
    # outlive the sessions; everything this verb owns is closed above).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def register(sub) -> None:
    v = sub.add_parser("view", help="relight a material live in the browser (local server on 127.0.0.1)")
    v.add_argument("material", help="material directory (its renderer.onnx is used when it matches)")
    v.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (default: %(default)s; 0: any free port)")
    v.add_argument("--no-open", action="store_true", help="do not open a browser tab")
    v.add_argument("--capture", help="capture directory whose photos the page shows beside the render (A/B)")
    v.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: one per core)")
    v.set_defaults(func=cmd_view)
