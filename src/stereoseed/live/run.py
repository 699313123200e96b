"""``stereoseed live``'s loop: look at the watched folder, insert each photo as it comes, push
the state to the page, and on stop (Ctrl-C, ``until`` photos, or ``stop`` set) finish the run
as ``reconstruct`` would (:class:`stereoseed.live.session.LiveRun`)."""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any, Callable

from stereoseed.config import Config
from stereoseed.errors import StereoseedError
from stereoseed.io.files import read_image
from stereoseed.live.config import LiveConfig
from stereoseed.live.page import LivePage
from stereoseed.live.session import LiveRun
from stereoseed.live.status import page_state
from stereoseed.live.video import VideoFeed
from stereoseed.live.watch import Arrival, FolderWatch, RigWatch
from stereoseed.output.result_set import result_name
from stereoseed.scene.camera_life import report_of

__all__ = ["run_live"]

log = logging.getLogger(__name__)


def _photo_line(name: str, report: dict[str, Any] | None, run: LiveRun) -> tuple[str, str]:
    """(the line said of a photo just inserted, its level)."""
    if report is None:
        return f"{name}: the pair's first photo; waiting for its second", "info"
    status = report.get("status", "")
    if status == "failed":
        return f"{name}: skipped: {report.get('reason')}", "warning"
    k = run.names.index(name)
    flag = run.recon.views[k].flag_reason if run.recon is not None and k < len(run.recon.views) else None
    if flag:
        return f"{name}: {status}, flagged: {flag}", "warning"
    return f"{name}: {status} ({report.get('new_points', 0)} new points)", "info"


def _report_of(run: LiveRun, name: str) -> dict[str, Any] | None:
    """The report of photo ``name`` as the model holds it (a rig station's left photo, inserted
    before its right one), None before the pair."""
    k = run.names.index(name)
    return None if run.recon is None or k >= len(run.recon.views) else report_of(run.recon.views[k].history)


def _pair_arrivals(pair: list[str | Path]) -> list[Arrival]:
    """The calibrated pair's two photos, given as files (before a video)."""
    if len(pair) != 2:
        raise StereoseedError(f"--pair takes the calibrated pair's two photos, got {len(pair)}")
    arrivals = []
    for path in map(Path, pair):
        read_image(path)  # a missing or unreadable photo of the pair: refused now, in one line
        arrivals.append(Arrival(path, path.name, path.read_bytes(), True, time.monotonic()))
    return arrivals


def run_live(watch: str | Path | None, calib: str | Path, out: str | Path, cfg: Config = Config(),
             live: LiveConfig = LiveConfig(), until: int | None = None, port: int = 0, resume: bool = False,
             on_start: Callable[[str], None] | None = None, on_line: Callable[[str], None] | None = None,
             stop: threading.Event | None = None, timings: list[dict[str, Any]] | None = None,
             video: str | Path | None = None, pair: list[str | Path] | None = None,
             realtime: bool = True, dense: bool = False, rig: str | Path | None = None) -> dict[str, Any]:
    """Watch ``watch`` for photos (or read the ``video`` after the ``pair``'s two photos) and
    reconstruct them live into the result folder ``out`` (``calib``: the pair's calibration, as
    for ``reconstruct``), the page on ``port`` of 127.0.0.1 (0: a free one). Stops on Ctrl-C,
    once ``until`` photos are taken, when ``stop`` is set, or when the video has ended; then
    finishes and writes the result folder. Returns the run's report.
    on_start(url): once the page is served; on_line(text): each line of the page's log.
    timings: when given, a dict per photo (name, settled_at, shown_at: monotonic seconds; the
    latter when a browser got the first state showing it, else None). realtime: a video read
    at its frame rate (False: as fast as the run takes its keyframes). dense: the dense stage
    once stopped, as ``reconstruct --dense`` runs it. rig: a stereo rig walked with both cameras:
    ``watch`` is the left camera's folder, this the right one's; a station is taken once both
    its photos are complete (:class:`~stereoseed.live.watch.RigWatch`), and ``until`` counts
    the photos of both."""
    if (watch is None) == (video is None):
        raise StereoseedError("give one source: --watch DIR or --video FILE")
    if rig is not None and video is not None:
        raise StereoseedError("--rig takes the right camera's folder beside --watch (the left one's); not with --video")
    if rig is not None and until is not None and until % 2:
        raise StereoseedError(f"--until {until}: a rig walk takes its photos two at a time (a station); give an "
                              f"even number")
    if rig is not None:
        first = []
        source: Any = RigWatch(watch, rig, live)  # folders that are not there: refused before the result folder
    elif video is not None:
        first = _pair_arrivals(pair or [])
        source = VideoFeed(video, cfg.video, live, realtime)
    else:
        first = []
        source = FolderWatch(watch, live)  # a folder that is not there: refused before the result folder is touched
    run = LiveRun(calib, out, cfg, resume, rig=rig is not None, dense=dense)
    try:
        page = LivePage(port, live, title=f"{result_name(out)} — stereoseed live")
    except BaseException:
        run.close()
        raise
    published: dict[str, int] = {}  # photo -> the version that first showed it
    step = 2 if rig is not None else 1  # photos taken together: a rig's station's two
    with page:
        def say(line: str, level: str = "info") -> None:
            (log.warning if level == "warning" else log.info)("%s", line)
            page.event(line, level)
            if on_line is not None:
                on_line(line)

        last_publish = [0.0]

        def publish(force: bool = False) -> None:
            """The state pushed when a photo is not shown yet: at once when ``force``d, else at
            most ``max_updates_per_s`` times a second."""
            if len(published) == len(run.names) and published:
                return  # nothing new to show
            if not force and time.monotonic() - last_publish[0] < 1.0 / live.max_updates_per_s:
                return
            version = page.publish(page_state(run.recon, run.names, run.unit))
            last_publish[0] = time.monotonic()
            for name in run.names:
                published.setdefault(name, version)

        try:
            source.mark_taken(run.names)
            if run.resumed:
                say(f"resumed: {len(run.resumed)} photos from the interrupted run")
            publish(force=True)
            if on_start is not None:
                on_start(page.url)
            if isinstance(source, VideoFeed):
                say(f"reading {source.path} at its pace ({source.fps:g} frames a second)")
                source.start()
            else:
                say(f"watching {source.folder} for photos")
            pending = [a for a in first if a.name not in run.names]

            def stopped() -> bool:
                return stop is not None and stop.is_set()

            while until is None or len(run.names) < until:
                if stopped():
                    say("stopping (Ctrl-C or a stop asked for)")
                    break
                look = source.look(time.monotonic())
                for note in look.notes:
                    say(note, "warning" if "ended" not in note else "info")
                arrivals, pending = pending + look.arrivals, []
                for group in (arrivals[i:i + step] for i in range(0, len(arrivals), step)):
                    if stopped() or (until is not None and len(run.names) + len(group) > until):
                        for arrival in group:
                            source.give_back(arrival.name)  # not this run's
                        continue
                    if group[0].name in run.names:  # a resumed video run: read again from its start
                        continue
                    report = run.add(*group)
                    for arrival in group:  # (a station's left photo: its report as the model holds it)
                        said = report if arrival is group[-1] else _report_of(run, arrival.name)
                        say(*_photo_line(arrival.name, said, run))
                    publish()
                publish(force=bool(arrivals))
                if isinstance(source, VideoFeed) and source.done and not arrivals:
                    for note in source.look(time.monotonic()).notes:
                        say(note)
                    break
                if not arrivals:
                    # (not stop.wait: a signal handler that sets stop while this thread holds
                    # the event's lock inside wait would wait on that lock for ever)
                    time.sleep(live.poll_s)
        except KeyboardInterrupt:
            say("stopping (Ctrl-C)")
        except BaseException:
            run.close()
            raise
        finally:
            if isinstance(source, VideoFeed):
                source.close()
        say(f"finishing {len(run.names)} photos as reconstruct would (the final adjustment, the loop closure, "
            f"the judgement of each camera)")
        publish(force=True)  # the photos not shown yet
        try:
            report = run.finish(dense)
        except BaseException as e:
            say(f"the run did not finish ({type(e).__name__}: {e}); run the same command with --resume", "warning")
            raise
        say(f"wrote {out}: {report['registered']} of {report['images']} photos placed, {report['points']} points")
        if timings is not None:
            for name, settled in zip(run.names, run.arrived):
                version = published.get(name)
                shown = min((t for v, t in page.delivered.items() if version is not None and v >= version),
                            default=None)
                timings.append({"name": name, "settled_at": settled, "shown_at": shown})
    return report
