"""What the compositor says about itself: the control socket's `status`, the run report (`summary`: the `stats`
telemetry each second, the control `report` and what `hmdrt run` writes at the end) and the frames log's header,
assembled from the compositor's parts. Only copies of the counts are taken under the lock that the render and
display threads share; the rest is worked out after it is released.
"""

from __future__ import annotations

import logging

import msgspec

from hmdrt.bus.security import open_to_local_users
from hmdrt.compositor.buffers import counts
from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.display import Display
from hmdrt.compositor.endpoints import Ingest
from hmdrt.compositor.parts import Parts
from hmdrt.compositor.session import Session
from hmdrt.compositor.sources import Sources
from hmdrt.telemetry.frames_log import FramesHeader
from hmdrt.version import __version__

log = logging.getLogger(__name__)


def frames_header(config: RunConfig, session: Session) -> FramesHeader:
    """The frames log's first line: the run, and the period and margin its frames are measured against."""
    profile = session.profile
    return FramesHeader(
        vsync_hz=profile.refresh_hz,
        period_ns=profile.period_ns,
        margin_ns=int(config.pacing.margin_ms * 1e6),
        virtual_time=config.run.virtual_time,
        method=session.spec,
        profile=profile.name,
        scene=session.scene.name,
        controller=config.controller.kind,
        seed=config.run.seed,
        config=config.source,
        hmdrt=__version__,
    )


def status(comp: Parts) -> dict:
    """The control socket's `status`: what renders, how it is paced, what has arrived and where the sockets are."""
    with comp.lock:
        pacing = comp.pacer.info()
        shown = dict(comp.report.shown)
    session = comp.session
    return {
        "method": session.spec,
        "params": session.params(),
        "profile": session.profile.name,
        "scene": session.scene.name,
        "vsync_hz": session.profile.refresh_hz,
        "shown": shown,
        "pacing": pacing,
        "devices": comp.store.devices,
        "drivers": {device: msgspec.to_builtins(status) for device, status in list(comp.ingest.status.items())},
        "endpoints": endpoints(comp),
        "security": security(comp),
    }


def endpoints(comp: Parts) -> dict[str, str]:
    """Where the three sockets are bound."""
    return {"ingest": comp.ingest.address, "telemetry": comp.telemetry.address, "control": comp.control.address}


def security(comp: Parts) -> dict:
    """Whether CURVE guards the bus and, if so, the handshakes it admitted and refused (clients without the
    keys are refused at the handshake, so their requests and samples never arrive); the sockets every local user
    can reach (tcp:// without CURVE); and the control commands and snapshot names refused."""
    refused = {"commands_refused": comp.control.unauthorised, "snapshots_refused": comp.snapshots_refused}
    open_to = {"open_to_local_users": open_to_local_users(endpoints(comp), comp.guard is not None)}
    if comp.guard is None:
        return {"curve": False, **open_to, **refused}
    return {"curve": True, **comp.guard.counts(), **open_to, **refused}


def warn_if_open(comp: Parts) -> None:
    """Say once, at start, which sockets every local user can reach (the run report's security says so too)."""
    bound = endpoints(comp)
    names = open_to_local_users(bound, comp.guard is not None)
    if names:
        log.warning(
            "%s: tcp:// without [security], which every local user can reach (to publish gaze, read the telemetry, "
            "ask for status); leave [bus] %s out for private ipc:// sockets, or add [security]",
            ", ".join(f"bus.{name} = {bound[name]}" for name in names),
            " and ".join(names),
        )


def rate_limited(comp: Parts) -> dict[str, dict]:
    """Per socket, the messages refused over their peer's budget and the seconds reading waited on the socket's
    (hmdrt.bus.limits)."""
    return {"ingest": comp.ingest.limiter.counts(), "control": comp.control.limiter.counts()}


def drivers(ingest: Ingest, sources: Sources) -> dict[str, dict]:
    """Per device, the samples that arrived on the bus and what was dropped or refused of them; and the counters of
    the drivers the compositor runs itself."""
    out = {}
    for device, status in ingest.status.items():
        out[device] = {
            "samples": status.samples,
            "dropped": status.dropped,
            "invalid": status.invalid,
            "malformed": status.malformed,
            "reconnects": status.reconnects,
        }
    out.update(sources.counters())
    return out


def display_info(session: Session) -> dict:
    """What the frames are rendered for: the profile, per-eye pixels, the eyes and the refresh rate."""
    profile = session.profile
    return {
        "profile": profile.name,
        "width": profile.width,
        "height": profile.height,
        "eyes": list(session.eyes),
        "refresh_hz": profile.refresh_hz,
    }


def image_buffers(session: Session, display: Display) -> dict[str, dict[str, int]]:
    """The rendered and warped images' pools: buffers held and allocated in all, steady after the first frames
    when no image is copied or leaked."""
    return {"rendered": counts(session.pools.values()), "warped": counts(display.warp_pools.values())}


def summary(comp: Parts) -> dict:
    """The run report so far; the percentiles, over every frame so far, are worked out outside the lock."""
    with comp.lock:
        snapshot, pacing = comp.report.snapshot(), comp.pacer.info()
    session, config = comp.session, comp.config
    report = snapshot.to_dict(
        method=session.method.name,
        method_spec=session.spec,
        profile=session.profile.name,
        display=display_info(session),
        scene=session.scene.name,
        drivers=drivers(comp.ingest, comp.sources),
        samples={device: {**vars(c), "dropped": c.dropped} for device, c in comp.store.counts().items()},
        pacing=pacing,
        virtual_time=config.run.virtual_time,
        seed=config.run.seed,
        ingest_malformed=comp.ingest.malformed,
        outages=comp.outages.to_dict(),
        devices_refused=comp.store.devices_refused,
        devices_expired=comp.store.devices_expired,
        statuses_refused=comp.ingest.statuses_refused,
        rate_limited=rate_limited(comp),
        **{key: value for sink in comp.sinks for key, value in sink.report().items()},
        config=config.source,
        hmdrt=__version__,
        security=security(comp),
        image_buffers=image_buffers(session, comp.display),
    )
    controller = comp.builder.controller
    if controller is not None:
        report["controller"] = {
            "kind": config.controller.kind,
            "target_miss_rate": config.controller.target_miss_rate,
            "level": controller.level,
            "at_floor": controller.at_floor,
            "foresight": controller.foresees,
            "changes": controller.changes,
            "trajectory": list(controller.trajectory),
        }
        if controller.foresees:  # what its predictions are held to now, and what a change of level has cost
            report["controller"]["fit"] = round(controller.fit, 3)
            report["controller"]["change_ms"] = round(controller.model.change_ns / 1e6, 3)
    return report
