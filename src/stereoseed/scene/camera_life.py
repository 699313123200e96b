"""A camera's life as types: its :class:`Status`, its :class:`Flag` and the events of its history.

A view is pending until the calibration gives its camera (``Calibrated``) or a registration
places it (``Registered``), or it cannot be placed (``Failed``). A placed camera may be
``Flagged`` (the run cannot vouch for it: an ambiguous choice, a zoom it cannot measure), have
its flag lifted, be judged after the last insertion (``Judged``: the final flag or none),
be ``Withdrawn`` (the next image could be placed only without it), ``RegisteredAgain`` (a
rival between its neighbours took its place) or ``Dropped`` (left undetermined by outlier
removal). The insertion's report (``Inserted``) is an event too: report.json's ``per_image``
entry of a view is rendered from its history (:func:`report_of`), never patched after the fact.

Only :class:`stereoseed.scene.reconstruction.Reconstruction` appends events; everything here is
an immutable value, so a history is shared freely between a model and its checkpoints.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any

__all__ = ["Status", "FlagKind", "Flag", "flag_kind", "Stage", "Event", "Calibrated", "Registered", "Inserted",
           "Failed", "Flagged", "FlagLifted", "Judged", "Withdrawn", "RegisteredAgain", "Dropped", "Life",
           "life_of", "report_of", "event_to_json", "event_from_json", "WITHDRAWN_FAILURE", "HINDSIGHT"]

# the report values the rendering writes (registration.base's FailureKind.WITHDRAWN and
# FoundBy.HINDSIGHT are these strings; scene/ sits below the policy that names them)
WITHDRAWN_FAILURE = "withdrawn after the next image"
HINDSIGHT = "between its neighbours"


class Status(StrEnum):
    """Where a view stands: its value is the first word of ``View.status``."""

    PENDING = "pending"  # not placed (yet, or again after a withdrawal)
    CALIBRATED = "calibrated"  # one of the calibrated pair: the frame itself
    REGISTERED = "registered"  # placed by a registration
    FAILED = "failed"  # could not be placed, or taken out; the reason says why


class FlagKind(StrEnum):
    """The kinds of flag a camera can carry; a flag's reason starts with its kind's value, so a
    result read back from its files gives the kind again (:func:`flag_kind`)."""

    AMBIGUOUS = "ambiguous: repeated structure"  # chosen on a margin over a rival a period away
    CONTRADICTED = "contradicted by the other cameras"  # its residuals after the final BA
    WEAK = "weak"  # too few observations of points two other cameras see
    UNCERTAIN = "uncertain"  # its position (or a zoom) measured too loosely


@dataclass(frozen=True)
class Flag:
    """Why the run cannot vouch for a camera: its ``kind`` and the ``detail`` with the figures.
    ``reason`` (also ``str(flag)``) is the text written to cameras.json and the reports: the
    kind, then ": detail", or " (detail)" for a detail in parentheses."""

    kind: FlagKind
    detail: str

    @property
    def reason(self) -> str:
        return f"{self.kind.value}{' ' if self.detail.startswith('(') else ': '}{self.detail}"

    def __str__(self) -> str:
        return self.reason

    def through(self, partner: str) -> Flag:
        """The same flag carried to the other image of a rig's station (``partner``: the image
        that carries it): a station is one rigid body."""
        return Flag(self.kind, f"{self.detail} (its station's {partner})")

    @classmethod
    def parse(cls, reason: str) -> Flag:
        """The flag whose :attr:`reason` is ``reason``; ValueError when no kind starts it."""
        for kind in FlagKind:
            for sep in (": ", " "):
                if reason.startswith(kind.value + sep):
                    return cls(kind, reason[len(kind.value) + len(sep):])
        raise ValueError(f"not a flag's reason: {reason[:60]!r}")


def flag_kind(reason: str) -> str:
    """The kind of a flag's ``reason`` read back from a file (a :class:`FlagKind`'s value; else
    the reason up to its details)."""
    return next((kind.value for kind in FlagKind if reason.startswith(kind)), reason.split(" (")[0])


class Stage(StrEnum):
    """When a flag was raised: while the camera was placed (its registration's evidence), or by
    the judgement after the last insertion."""

    PLACED = "placed"
    JUDGED = "judged"


# ----------------------------------------------------------------------------------- events
@dataclass(frozen=True)
class Event:
    """One step of a view's history."""


@dataclass(frozen=True)
class Calibrated(Event):
    """The calibration gives the camera (one of the calibrated pair)."""


@dataclass(frozen=True)
class Registered(Event):
    """A registration placed the camera (``found_by``: what placed it)."""

    found_by: str


@dataclass(frozen=True)
class Inserted(Event):
    """The view's step of the run is done (the pair matched and triangulated; an insertion's
    points added and its window adjusted): ``report`` is what it did (the report's entry)."""

    report: dict[str, Any] = field(compare=False)


@dataclass(frozen=True)
class Failed(Event):
    """The view could not be placed: ``reason`` for a user, ``report`` the attempt's entry."""

    reason: str
    report: dict[str, Any] = field(compare=False)


@dataclass(frozen=True)
class Flagged(Event):
    """The run cannot vouch for the camera: ``flag``, raised at ``stage``."""

    flag: Flag
    stage: Stage = Stage.PLACED


@dataclass(frozen=True)
class FlagLifted(Event):
    """Later evidence lifts the camera's flag: ``why``."""

    why: str


@dataclass(frozen=True)
class Judged(Event):
    """The judgement after the last insertion: the camera's final flag (None: vouched for)."""

    flag: Flag | None


@dataclass(frozen=True)
class Withdrawn(Event):
    """Taken out of the model: the next image could be placed only without it (``reason``)."""

    reason: str


@dataclass(frozen=True)
class RegisteredAgain(Event):
    """A camera found between its neighbours took its place: ``found`` says what and how."""

    found: str


@dataclass(frozen=True)
class Dropped(Event):
    """Taken out at the end: outlier removal left its camera undetermined (``reason``)."""

    reason: str


# ----------------------------------------------------------------------------- the state
@dataclass(frozen=True)
class Life:
    """A view's state as its history leaves it: ``status``, ``reason`` (a failure's), what placed
    the camera (``found_by``), the flag raised while it was placed and still standing
    (``placement_flag``), and its current flag (``flag``: the judgement's once judged)."""

    status: Status = Status.PENDING
    reason: str | None = None
    found_by: str | None = None
    placement_flag: Flag | None = None
    flag: Flag | None = None

    def after(self, event: Event) -> Life:
        """The state after ``event``."""
        if isinstance(event, Calibrated):
            return Life(Status.CALIBRATED)
        if isinstance(event, Registered):
            return Life(Status.REGISTERED, found_by=event.found_by)
        if isinstance(event, Flagged):
            if event.stage == Stage.JUDGED:
                return Life(self.status, self.reason, self.found_by, self.placement_flag, event.flag)
            return Life(self.status, self.reason, self.found_by, event.flag, event.flag)
        if isinstance(event, FlagLifted):
            return Life(self.status, self.reason, self.found_by)
        if isinstance(event, Judged):
            return Life(self.status, self.reason, self.found_by, self.placement_flag, event.flag)
        if isinstance(event, RegisteredAgain):
            return Life(self.status, self.reason, HINDSIGHT)
        if isinstance(event, (Failed, Withdrawn, Dropped)):
            return Life(Status.FAILED, event.reason)
        return self  # Inserted: the state is the registration's

    @property
    def text(self) -> str:
        """``View.status``: the status, and for a failure its reason ("failed: ...")."""
        return f"{self.status.value}: {self.reason}" if self.status == Status.FAILED else self.status.value


def life_of(history: tuple[Event, ...]) -> Life:
    """The state a history leaves a view in."""
    life = Life()
    for event in history:
        life = life.after(event)
    return life


def _superseded(report: dict[str, Any], under: str, **now: Any) -> dict[str, Any]:
    """``report`` with what its registration said moved under ``under`` (none of it is the
    model's now), and ``now`` in its place."""
    return {"image": report["image"], **now,
            under: {key: value for key, value in report.items() if key not in ("image", "status")}}


def report_of(history: tuple[Event, ...]) -> dict[str, Any] | None:
    """The view's entry of the run's report (``per_image``), rendered from its history: the
    report of the event that placed it or failed it, then what happened since (withdrawn: it
    failed, its registration under "withdrawn_registration"; registered again: its first
    registration under "first_registration"; dropped: it failed, with the reason). None for a
    view the run has not reached."""
    report = None
    for event in history:
        if isinstance(event, (Inserted, Failed)):
            report = dict(event.report)
        elif report is None:
            continue
        elif isinstance(event, Withdrawn):
            report = _superseded(report, "withdrawn_registration", status="failed", reason=event.reason,
                                 failure=WITHDRAWN_FAILURE)
        elif isinstance(event, RegisteredAgain):
            report = _superseded(report, "first_registration", status=report["status"], registered_by=HINDSIGHT,
                                 registered_again=event.found)
        elif isinstance(event, Dropped):
            report = {**report, "status": "failed", "reason": event.reason}
    return report


# ------------------------------------------------------------------- to and from JSON
_EVENTS = {cls.__name__: cls for cls in (Calibrated, Registered, Inserted, Failed, Flagged, FlagLifted, Judged,
                                         Withdrawn, RegisteredAgain, Dropped)}


def event_to_json(event: Event) -> dict[str, Any]:
    """A JSON-able dict of ``event`` (for the checkpoint)."""
    out: dict[str, Any] = {"event": type(event).__name__}
    for f in fields(event):
        value = getattr(event, f.name)
        out[f.name] = value.reason if isinstance(value, Flag) else value
    return out


def event_from_json(data: Any) -> Event:
    """The event :func:`event_to_json` wrote; ValueError on anything else (a checkpoint read
    back is checked, not trusted)."""
    if not isinstance(data, dict) or data.get("event") not in _EVENTS:
        raise ValueError("not an event of a view's history")
    cls = _EVENTS[data["event"]]
    names = {f.name for f in fields(cls)}
    if set(data) != names | {"event"}:
        raise ValueError(f"a malformed {cls.__name__} event")
    values = {}
    for name in names:
        value = data[name]
        if name == "report":
            if not isinstance(value, dict):
                raise ValueError(f"a {cls.__name__} event without its report")
        elif name == "flag":
            value = None if value is None and cls is Judged else Flag.parse(_text(value))
        elif name == "stage":
            value = Stage(_text(value))
        else:
            value = _text(value)
        values[name] = value
    return cls(**values)


def _text(value: Any) -> str:
    if not isinstance(value, str):
        raise ValueError("an event's text is not a string")
    return value
