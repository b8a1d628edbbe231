r"""Component life cycle and a supervisor that restarts failed components.

The switching paper (Hu et al.; ``docs/background.md#references``; sec. 3, Fig. 6b) runs every
localizer as an RT-component with a life cycle: "When a component is started, it is in
the ready state, in which it has completed the initialization process. And then the
component can be activated to execute the core algorithm repeatedly. It remains in the
active state until it is deactivated or an error occurs. When an error occurs in the
core algorithm, a reset can be performed and the component will shift back to the
ready state." The states and the transitions allowed here::

    created --initialize--> ready --activate--> active --deactivate--> ready
                              |                   |
                              | (activation       | fail (error in the core algorithm,
                              |  failed)          |       health check, heartbeat lost)
                              v                   v
                            error <-------------- +
                              |  ^
                        reset |  | (reset failed)
                              v  |
                            reset --(reset done)--> ready

Any other transition raises :class:`InvalidTransition`. (The RTC life cycle's
"inactive" state is called *ready* here, after the paper's text.)

The paper's configuration component "acts like a supervisor": it monitors the
components' health and, "once the execution error occurs, the current configuration
will be changed. At the same time, the problem component will be restarted".
:class:`Supervisor` does that: :meth:`Supervisor.check` fails an active component whose
health callback returns false (or raises) or whose heartbeat is older than its
timeout, and restarts a failed one (``error -> reset -> ready -> active``) once its
``restart_delay`` has passed. While a component is not active, and after a restart
until it reports a new estimate, its :class:`~dfusion.estimation.Estimate`
carries ``healthy=False``: switching policies count it as reliability 0 and fusion
policies leave it out, so it is off the candidates meanwhile.

Times are explicit arguments (``t`` / ``now``), defaulting to the component's or
supervisor's ``clock`` (``time.monotonic``); simulations pass their own time.
"""
from __future__ import annotations

import enum
import logging
import math
import time
from dataclasses import replace
from typing import Callable, Iterable, NamedTuple

from dfusion.errors import DfusionError, ValidationError
from dfusion.estimation.estimate import Estimate

log = logging.getLogger(__name__)

__all__ = ["State", "TRANSITIONS", "InvalidTransition", "Component", "Supervisor", "LifecycleEvent"]


class InvalidTransition(DfusionError, RuntimeError):
    """A life-cycle transition that Fig. 6b does not allow."""


class State(str, enum.Enum):
    CREATED = "created"
    READY = "ready"
    ACTIVE = "active"
    ERROR = "error"
    RESET = "reset"

    def __str__(self) -> str:
        return self.value


#: Allowed transitions ``from -> {to}``.
TRANSITIONS: dict[State, frozenset[State]] = {
    State.CREATED: frozenset({State.READY}),
    State.READY: frozenset({State.ACTIVE, State.ERROR}),
    State.ACTIVE: frozenset({State.READY, State.ERROR}),
    State.ERROR: frozenset({State.RESET}),
    State.RESET: frozenset({State.READY, State.ERROR}),
}


class LifecycleEvent(NamedTuple):
    """One state change: time, component, from, to, reason."""

    t: float
    component: str
    from_: State
    to: State
    reason: str


class Component:
    """A supervised component (a localizer) with the life cycle of the module docstring.

    Parameters
    ----------
    name : str
        Also the name of its source estimates.
    health : callable, optional
        ``health() -> bool``; false (or an exception) means the core algorithm failed.
    heartbeat_timeout : float, optional
        Seconds without :meth:`heartbeat` or :meth:`report` after which an active
        component is declared failed.
    on_initialize, on_activate, on_deactivate, on_reset : callable, optional
        Hooks run on the transitions. An exception in ``on_activate`` sends the
        component to *error*; in ``on_reset``, back to *error* (the reset failed); in
        ``on_initialize``, the component stays *created* and the exception propagates.
    clock : callable
        Default time source.
    """

    def __init__(
        self,
        name: str,
        *,
        health: Callable[[], bool] | None = None,
        heartbeat_timeout: float | None = None,
        on_initialize: Callable[[], None] | None = None,
        on_activate: Callable[[], None] | None = None,
        on_deactivate: Callable[[], None] | None = None,
        on_reset: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise ValidationError("component name must be a non-empty string")
        if heartbeat_timeout is not None and not (heartbeat_timeout > 0):
            raise ValidationError("heartbeat_timeout must be positive")
        self.name = name
        self.health = health
        self.heartbeat_timeout = None if heartbeat_timeout is None else float(heartbeat_timeout)
        self.on_initialize = on_initialize
        self.on_activate = on_activate
        self.on_deactivate = on_deactivate
        self.on_reset = on_reset
        self.clock = clock
        self.state = State.CREATED
        self.history: list[LifecycleEvent] = []
        self.error_reason = ""
        self.failed_at: float | None = None
        self.activated_at: float | None = None
        self.last_heartbeat: float | None = None
        self.last_report: float | None = None
        self.estimate: Estimate | None = None
        self.failures = 0
        self.restarts = 0
        self._listeners: list[Callable[[LifecycleEvent], None]] = []

    def __repr__(self) -> str:
        return f"Component({self.name!r}, state={self.state.value})"

    def _t(self, t: float | None) -> float:
        return float(self.clock() if t is None else t)

    def transition(self, to: State | str, reason: str = "", t: float | None = None) -> LifecycleEvent:
        """Move to ``to`` if Fig. 6b allows it; raises :class:`InvalidTransition` otherwise."""
        to = State(to)
        if to not in TRANSITIONS[self.state]:
            raise InvalidTransition(f"{self.name}: {self.state.value} -> {to.value} is not allowed "
                                    f"(allowed: {sorted(s.value for s in TRANSITIONS[self.state])})")
        ev = LifecycleEvent(self._t(t), self.name, self.state, to, reason)
        self.state = to
        self.history.append(ev)
        for cb in self._listeners:
            cb(ev)
        return ev

    # ---------------------------------------------------------------- life-cycle operations
    def initialize(self, t: float | None = None) -> None:
        """``created -> ready`` (runs ``on_initialize`` first)."""
        if self.state is not State.CREATED:
            raise InvalidTransition(f"{self.name}: initialize from {self.state.value}")
        if self.on_initialize:
            self.on_initialize()
        self.transition(State.READY, "initialized", t)

    def activate(self, t: float | None = None) -> bool:
        """``ready -> active``; ``ready -> error`` if ``on_activate`` raises. True if active."""
        if self.state is not State.READY:
            raise InvalidTransition(f"{self.name}: activate from {self.state.value}")
        t = self._t(t)
        if self.on_activate:
            try:
                self.on_activate()
            except Exception as exc:  # noqa: BLE001 - a failing component must not stop the supervisor
                self.fail(f"activation failed: {exc}", t)
                return False
        self.transition(State.ACTIVE, "activated", t)
        self.activated_at = t
        self.last_heartbeat = t
        return True

    def deactivate(self, t: float | None = None) -> None:
        """``active -> ready``."""
        if self.state is not State.ACTIVE:
            raise InvalidTransition(f"{self.name}: deactivate from {self.state.value}")
        if self.on_deactivate:
            self.on_deactivate()
        self.transition(State.READY, "deactivated", t)

    def fail(self, reason: str = "error", t: float | None = None) -> None:
        """``active -> error`` (or ``ready``/``reset -> error``): an error occurred."""
        t = self._t(t)
        self.transition(State.ERROR, reason, t)
        self.error_reason = reason
        self.failed_at = t
        self.failures += 1

    def reset(self, t: float | None = None) -> bool:
        """``error -> reset -> ready`` (``reset -> error`` if ``on_reset`` raises). True if ready."""
        t = self._t(t)
        self.transition(State.RESET, "reset", t)
        if self.on_reset:
            try:
                self.on_reset()
            except Exception as exc:  # noqa: BLE001
                self.fail(f"reset failed: {exc}", t)
                return False
        self.transition(State.READY, "reset done", t)
        self.restarts += 1
        self.error_reason = ""
        return True

    # ---------------------------------------------------------------- data and liveness
    def heartbeat(self, t: float | None = None) -> None:
        """The component is alive at ``t``."""
        self.last_heartbeat = self._t(t)

    def report(self, estimate: Estimate, t: float | None = None) -> None:
        """The component's newest estimate (also a heartbeat). Ignored unless active."""
        if self.state is not State.ACTIVE:
            return
        t = self._t(t)
        if estimate.name != self.name:
            estimate = replace(estimate, name=self.name)
        self.estimate = estimate
        self.last_report = t
        self.last_heartbeat = t

    @property
    def active(self) -> bool:
        return self.state is State.ACTIVE

    def source(self) -> Estimate | None:
        """The last estimate, ``healthy`` only if active and reported since the activation."""
        e = self.estimate
        if e is None:
            return None
        fresh = self.active and self.last_report is not None and self.activated_at is not None \
            and self.last_report >= self.activated_at
        return e if e.healthy == fresh else replace(e, healthy=fresh and e.healthy)

    def on_transition(self, callback: Callable[[LifecycleEvent], None]) -> None:
        """Call ``callback(event)`` after every transition."""
        self._listeners.append(callback)


class Supervisor:
    """Monitors components' health and restarts failed ones (the paper's configuration component).

    Parameters
    ----------
    components : iterable of Component
    restart : bool
        Restart failed components (``error -> reset -> ready``).
    restart_delay : float
        Seconds a failed component stays in *error* before the reset (the time a real
        restart takes; the component is off the candidates meanwhile).
    reactivate : bool
        Activate a component again after a successful reset.
    max_restarts : int, optional
        Give up on a component after this many failed-and-restarted cycles.
    clock : callable
        Default time source for :meth:`check`.

    ``events`` records every transition of every supervised component.
    """

    def __init__(
        self,
        components: Iterable[Component] = (),
        *,
        restart: bool = True,
        restart_delay: float = 0.0,
        reactivate: bool = True,
        max_restarts: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(restart_delay) and restart_delay >= 0):
            raise ValidationError("restart_delay must be >= 0")
        self.restart = bool(restart)
        self.restart_delay = float(restart_delay)
        self.reactivate = bool(reactivate)
        self.max_restarts = max_restarts
        self.clock = clock
        self.components: dict[str, Component] = {}
        self.events: list[LifecycleEvent] = []
        for c in components:
            self.add(c)

    def add(self, component: Component) -> Component:
        if component.name in self.components:
            raise ValidationError(f"duplicate component {component.name!r}")
        self.components[component.name] = component
        component.on_transition(self.events.append)
        return component

    def __getitem__(self, name: str) -> Component:
        return self.components[name]

    def start(self, t: float | None = None) -> None:
        """Initialize every created component and activate every ready one."""
        t = float(self.clock() if t is None else t)
        for c in self.components.values():
            if c.state is State.CREATED:
                c.initialize(t)
            if c.state is State.READY:
                c.activate(t)

    def check(self, now: float | None = None) -> list[LifecycleEvent]:
        """One supervision round at ``now``; returns the transitions it caused."""
        now = float(self.clock() if now is None else now)
        n0 = len(self.events)
        for c in self.components.values():
            if c.state is State.ACTIVE:
                reason = self._failure(c, now)
                if reason:
                    log.warning("%s failed: %s", c.name, reason)
                    c.fail(reason, now)
            if c.state is State.ERROR and self.restart:
                if self.max_restarts is not None and c.restarts >= self.max_restarts:
                    continue
                if c.failed_at is None or now >= c.failed_at + self.restart_delay:
                    if c.reset(now) and self.reactivate:
                        c.activate(now)
        return self.events[n0:]

    @staticmethod
    def _failure(c: Component, now: float) -> str:
        if c.health is not None:
            try:
                if not c.health():
                    return "health check failed"
            except Exception as exc:  # noqa: BLE001
                return f"health check raised {exc!r}"
        if c.heartbeat_timeout is not None and c.last_heartbeat is not None \
                and now - c.last_heartbeat > c.heartbeat_timeout:
            return f"no heartbeat for {now - c.last_heartbeat:.3g} s"
        return ""

    def sources(self) -> list[Estimate]:
        """The components' latest estimates, ``healthy=False`` for those not usable now."""
        return [s for s in (c.source() for c in self.components.values()) if s is not None]

    def report_to(self, node, now: float | None = None) -> None:
        """:meth:`check`, then ``node.report_source`` of every component's estimate."""
        self.check(now)
        for s in self.sources():
            node.report_source(s)
