"""`stereoseed live`: photos reconstructed as they arrive, the model in a page on 127.0.0.1."""
from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from collections.abc import Iterator

from stereoseed.cli._terminal import on_main_thread, say
from stereoseed.cli.arguments import whole_number
from stereoseed.errors import StereoseedError


def _cmd_live(args: argparse.Namespace) -> int:
    from stereoseed.config import Config
    from stereoseed.live import run_live

    cfg = Config.from_file(args.config) if args.config else Config()
    if args.video is not None and args.pair is None:
        raise StereoseedError("--video needs the calibrated pair's two photos first: --pair PAIR1.png PAIR2.png")
    stop = threading.Event()
    with _stop_asked(stop):
        report = run_live(args.watch, args.calib, args.out, cfg, until=args.until, port=args.port, resume=args.resume,
                          video=args.video, pair=args.pair, dense=args.dense, rig=args.rig, stop=stop,
                          on_start=lambda url: say(f"live page: {url}  (Ctrl-C: stop and write {args.out})"),
                          on_line=None if args.quiet else say)
    say(f"{report['registered']}/{report['images']} photos placed, {report['points']} points; wrote {args.out}")
    return 0


@contextlib.contextmanager
def _stop_asked(stop: threading.Event) -> Iterator[None]:
    """Ctrl-C (and SIGTERM) while the walk goes on ask it to stop: ``stop`` is set, the photo
    under way is placed, and the run finishes and writes as after ``--until``. An exception
    raised at whatever line the main thread was on could leave a lock it held taken (the page's,
    the dense worker pool's: a run that never ended, seen under load in the suite); the main
    thread never waits on ``stop`` itself (live.run sleeps between looks), so setting it here
    cannot wait on a lock this thread holds. A second one raises KeyboardInterrupt where the run
    is: in the walk, the run still finishes; while finishing, it stops and ``--resume``
    continues. Only from the main thread (signals go there)."""
    if not on_main_thread():
        yield
        return

    def ask(signum, frame) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    before = {s: signal.signal(s, ask) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in before.items():
            if handler is not None:  # (None: a handler installed from C, which cannot be put back)
                signal.signal(s, handler)


# --until: the calibrated pair first; --port: 0 lets the system pick a free one
_count = whole_number(2, note="the calibrated pair")
_port = whole_number(0, 65535, what="a port number", note="0: a free one")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the live subcommand."""
    p = sub.add_parser("live", help="reconstruct photos as they arrive in a folder, the model growing in a page "
                                    "on 127.0.0.1 (docs/live.md)")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--watch", metavar="DIR",
                   help="the folder the photos arrive in (synced from a phone, a tethered camera); the first two are "
                        "the calibrated pair; photos already there are taken first, in the order they were written")
    source.add_argument("--video", metavar="FILE",
                        help="a filmed walk, read at its own pace, its keyframes picked as reconstruct picks them "
                             "(with --pair); or a camera filming now (its number: 0 is the first) or a stream's "
                             "address (rtsp://..., http://...)")
    p.add_argument("--pair", nargs=2, metavar=("PAIR1", "PAIR2"),
                   help="with --video: the calibrated pair's two photos (the video starts where the second was taken)")
    p.add_argument("--rig", metavar="DIR",
                   help="a stereo rig walked with both cameras: the right camera's photos arrive in DIR, the left "
                        "one's in --watch; a station is placed once both its photos are there (as reconstruct --rig)")
    p.add_argument("--calib", required=True, help="the pair's calibration, as for reconstruct")
    p.add_argument("--out", required=True, help="result folder, written as reconstruct writes it when the run stops")
    p.add_argument("--until", type=_count, metavar="N", help="stop after N photos (default: Ctrl-C)")
    p.add_argument("--port", type=_port, default=8765,
                   help="the page's port on 127.0.0.1 (default: %(default)s; 0: a free one, printed)")
    p.add_argument("--dense", action="store_true",
                   help="once stopped, the quasi-dense stage as reconstruct --dense runs it (dense.ply)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted live run into the same --out")
    p.add_argument("--config", metavar="FILE", help="the run's settings: a TOML file (docs/config.md)")
    p.add_argument("--quiet", action="store_true", help="print only the page's address, errors and the summary")
    p.add_argument("--verbose", action="store_true", help="log each step")
    p.set_defaults(func=_cmd_live)
