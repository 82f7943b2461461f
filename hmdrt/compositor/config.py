"""The run configuration of `hmdrt run CONFIG.toml`: display, scene, method, drivers, bus, pacing,
prediction, gaze, controller and output, validated on load with every mistake reported in one line.

Paths in the file (a replay:// trace, hid://stub's trace=, the report, the frames folder) are relative
to the config file, so a config runs the same from any working directory.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import msgspec

from hmdrt.drivers import DriverUrl, driver_class
from hmdrt.errors import ConfigError
from hmdrt.files.configfile import convert, read_toml
from hmdrt.foveation import MethodChoice

Ms = Annotated[float, msgspec.Meta(ge=0.0, le=10_000.0)]
Eyes = Literal["left", "right", "both"]


class _Section(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    pass


class Display(_Section):
    profile: str = "sim-cpu-640"  # a built-in profile name or a .toml profile (its refresh rate sets the VSync)
    eyes: Eyes = "both"
    resolution: str = ""  # per-eye WIDTHxHEIGHT overriding the profile's, same field of view
    refresh_hz: Annotated[float, msgspec.Meta(ge=0.0, le=1000.0)] = 0.0  # 0: the profile's


class Method(_Section):
    name: str = "rrm"  # a method, with options as in "weier16?frc=small"
    options: dict[str, str | int | float | bool] = {}


class Driver(_Section):
    url: str


class Bus(_Section):
    """The three sockets' endpoints; "": ipc:// in a folder of this user's only (hmdrt.bus.local). A tcp:// one
    without [security] is open to every local user (loopback) or refused (any other address)."""

    ingest: str = ""  # the SUB drivers publish to
    telemetry: str = ""  # the PUB of `frame`, `stats`, `log` and `preview`
    control: str = ""  # the control socket; tcp:// without [security] answers reads only


class Security(_Section):
    """CURVE on all three sockets, needed to bind anything but loopback (README "Access"); key files of `hmdrt keys`."""

    server_key: str  # the compositor's secret key file, NAME.key_secret
    allowed_clients: Annotated[list[str], msgspec.Meta(min_length=1)]  # public key files (NAME.key) of the clients


class Pacing(_Section):
    margin_ms: Ms = 2.0  # fixed margin before the VSync (docs/architecture.md, Pacer: 1-2 ms)
    present_to_display_ms: Annotated[float, msgspec.Meta(ge=-1.0, le=1000.0)] = -1.0  # -1: half the period
    render_delay_ms: Ms = 0.0  # extra time added to every render, to see how misses are handled
    # the wake-up plans for this quantile of the last tail_window render times (0: the filtered mean, as Monado);
    # with the largest of the last W, about 1 frame in W + 1 exceeds the plan: bench/pacing.py replays measured
    # render times through each (default config: 90 -> 0.45% misses, 300 -> 0.28% for 3.3 ms earlier wake-ups)
    tail_quantile: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 1.0
    tail_window: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 300


class Prediction(_Section):
    horizon_ms: Ms = 50.0  # gaze and pose are extrapolated at most this far past the newest sample
    gaze_device: str = ""  # "": the device with the newest gaze
    pose_device: str = ""


class GazePath(_Section):
    """The compositor's gaze estimates at display time (hmdrt.compositor.samples)."""

    # predict a saccade's flight and landing point from its velocity profile and the main sequence, and, while
    # a prediction stands, show frames along it rather than extrapolating the gaze velocity (hmdrt.tracking.saccade)
    saccade_prediction: bool = False


class Fallback(_Section):
    """When the gaze device goes silent (hmdrt.compositor.fallback)."""

    stale_ms: Annotated[float, msgspec.Meta(gt=0.0, le=60_000.0)] = 250.0  # silent this long: an outage
    widen_deg_per_s: Annotated[float, msgspec.Meta(ge=0.0, le=1000.0)] = 20.0  # then the fovea widens this fast
    max_widen_deg: Annotated[float, msgspec.Meta(ge=0.0, le=90.0)] = 20.0
    centre_after_ms: Annotated[float, msgspec.Meta(gt=0.0, le=600_000.0)] = 2000.0  # then the screen centre

    def __post_init__(self) -> None:
        if self.centre_after_ms < self.stale_ms:
            raise ValueError(f"centre_after_ms ({self.centre_after_ms}) must not be below stale_ms ({self.stale_ms})")


class Controller(_Section):
    kind: Literal["none", "hold-budget"] = "none"
    target_miss_rate: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 0.05
    headroom: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.85
    widen_latency_ms: Ms = 0.0  # widen the fovea by gaze speed times this tracker latency
    accuracy_deg: Annotated[float, msgspec.Meta(ge=0.0, le=30.0)] = 0.0  # and by this tracker accuracy
    foresight: bool = True  # each frame's level from its predicted render time (a probe of the fovea), not feedback


class Output(_Section):
    report: str = ""  # run report JSON ("" : none unless --report)
    frames_dir: str = ""  # presented frames as PNG ("" : none)
    video: str = ""  # presented frames as an H.264 video at refresh / every fps ("": none; the video extra)
    every: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)] = 1  # every Nth VSync, to frames_dir and video
    snapshot_dir: str = ""  # where the control `snapshot` writes, by file name ("": the folder hmdrt run started in)
    frames_log: str = ""  # every frame record as JSON Lines, appended and flushed ("": none)


class Lsl(_Section):
    """Lab Streaming Layer outlets of what was shown (hmdrt.compositor.lsl_outlets); needs the `lsl` extra."""

    outlets: list[Literal["frames", "samples"]] = []  # frames: a marker per VSync; samples: each frame's gaze and pose


class Run(_Section):
    seed: int = 0
    threads: Annotated[int, msgspec.Meta(ge=0, le=256)] = 0  # tracing threads (0: all cores)
    # numba threads of the render and display threads' per-pixel kernels (0: all cores; "auto": 1 on a machine of
    # 2 cores or fewer, where a parallel kernel waits for a core the display, ingest and drivers want, else all)
    kernel_threads: Annotated[int, msgspec.Meta(ge=0, le=256)] | Literal["auto"] = "auto"
    virtual_time: bool = False
    frames: Annotated[int, msgspec.Meta(ge=0)] = 0  # stop after this many VSyncs (0: until stopped)
    duration_s: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0  # or after this long
    warmup_s: Annotated[float, msgspec.Meta(ge=0.0)] = 2.0  # the report also gives the miss rate after this


class RunConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    scene: str = "whitted"
    display: Display = Display()
    method: Method = Method()
    drivers: list[Driver] = []
    bus: Bus = Bus()
    security: Security | None = None  # None: every socket binds loopback, local clients are trusted
    pacing: Pacing = Pacing()
    prediction: Prediction = Prediction()
    gaze: GazePath = GazePath()
    controller: Controller = Controller()
    fallback: Fallback = Fallback()
    output: Output = Output()
    lsl: Lsl = Lsl()
    run: Run = Run()
    source: str = ""  # the file it was read from (set on load)

    @property
    def method_choice(self) -> MethodChoice:
        """The [method] section parsed: its name (with any "?key=value&...") and options (ConfigError if bad)."""
        return MethodChoice.parse(self.method.name, **self.method.options)


RESTART_ONLY = ("scene", "display", "drivers", "bus", "security", "lsl")  # a running compositor cannot change these


def reload_plan(old: RunConfig, new: RunConfig) -> tuple[RunConfig, list[str]]:
    """What a reload of `new` over the running `old` applies, and the changes it cannot apply that need a
    restart: the restart-only sections and the video with its rate (its encoder is fixed) stay as they run, and
    so does [run] (seed, threads, limits)."""
    restart = [k for k in RESTART_ONLY if getattr(new, k) != getattr(old, k)]
    output = new.output
    if output.video != old.output.video or (old.output.video and output.every != old.output.every):
        restart.append("output.video and output.every")
        output = msgspec.structs.replace(output, video=old.output.video, every=old.output.every)
    kept = {k: getattr(old, k) for k in (*RESTART_ONLY, "run")}
    return msgspec.structs.replace(new, output=output, **kept), restart


def _relative(url: str, base: Path) -> str:
    """A driver URL with the file paths its driver declares (replay://PATH, hid://stub?trace=PATH) made absolute
    against base; a URL that does not parse, or names no driver, is a ConfigError or DriverNotFound."""
    parsed = DriverUrl.parse(url)
    return driver_class(parsed.scheme).with_paths_under(parsed, base).text


def load_config(path: str | Path | None = None, **overrides) -> RunConfig:
    """A validated RunConfig from a TOML file (None: the defaults), with paths resolved against the file."""
    data: dict = {}
    base = Path.cwd()
    if path is not None:
        data = read_toml(path)
        base = Path(path).resolve().parent
    if not isinstance(data.setdefault("run", {}), dict):
        raise ConfigError(f"{path}: [run] must be a table, got {type(data['run']).__name__}")
    data["run"].update({k: v for k, v in overrides.items() if v is not None})
    config = convert(data, RunConfig, path)
    drivers = [Driver(_relative(d.url, base)) for d in config.drivers]
    output = config.output
    output = msgspec.structs.replace(
        output,
        report=str(base / output.report) if output.report else "",
        frames_dir=str(base / output.frames_dir) if output.frames_dir else "",
        snapshot_dir=str(base / output.snapshot_dir) if output.snapshot_dir else str(Path.cwd()),
        video=str(base / output.video) if output.video else "",
        frames_log=str(base / output.frames_log) if output.frames_log else "",
    )
    if config.security is not None:
        keys = config.security
        security = Security(str(base / keys.server_key), [str(base / p) for p in keys.allowed_clients])
        config = msgspec.structs.replace(config, security=security)
    return msgspec.structs.replace(config, drivers=drivers, output=output, source=str(path or ""))
