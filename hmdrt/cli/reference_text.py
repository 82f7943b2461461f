"""The prose of docs/reference.md (hmdrt.cli.reference puts it between what it makes from the parser, the control
commands and the config schemas), and the meaning of each config key: a key the schema has and this file does
not explain, or explains and the schema has not, stops the reference from being made."""

HEADER = """\
# Reference

<!-- Made by `python -m hmdrt.cli.reference > docs/reference.md` from the parser, the control commands
(hmdrt/compositor/commands.py) and the config schemas; the prose is in hmdrt/cli/reference_text.py. Edit those,
not this file: tests/test_cli_reference.py fails when it differs from what they make. -->

The `hmdrt` command line, the run config of `hmdrt run` and the eval config
of `hmdrt eval`. Errors are reported as one line, never a traceback. For what
the numbers mean (bus, report keys, conventions) see `docs/architecture.md`.

Sections: [Command line](#command-line), [Control socket](#control-socket), [Run config](#run-config),
[Eval config](#eval-config).

## Command line

The help texts below are printed by `hmdrt --help` and
`hmdrt SUBCOMMAND --help` (also `python -m hmdrt ...`)."""

# after a subcommand's help, by its words after `hmdrt`
AFTER_HELP = {
    "emulate": """\
`hmdrt emulate lsl` publishes a Lab Streaming Layer stream of type `Gaze` laid
out as TittaLSL publishes a Tobii tracker's (120 Hz by default; LSL's
discovery finds it, so it takes no `--port`, and `--host` does not apply) and
prints its `lsl://?source_id=...` URL (`docs/protocols.md`, section 9.4).

`lsl://` options (`docs/protocols.md`, section 9):

| Option | Default | Meaning |
|---|---|---|
| `type` | `Gaze` | the stream type to resolve |
| `name` | - | the stream's LSL name to resolve; also the bus device name (default `lsl`) |
| `source_id` | - | the stream's source_id to resolve |
| `timeout` | `5` | seconds to find the stream, read its meta-data and clock offset (0.1-60) |
| `axes` | `head` | the axes of the stream's 3D vectors: `head` (x right, y up, z back; Tobii), \
`opencv` (y down, z forward; Pupil Core), `unity` (y up, z forward) |
| `profile` | `sim-cpu-640` | the HMD profile whose eye screens ScreenX/Y positions lie on |
| `origin` | `top-left` | where ScreenX/Y start: `top-left` (Tobii, pixels) or `bottom-left` (Pupil's norm_pos) |
| `confidence` | `0.6` | the least Confidence at which an eye counts (0-1) |

Exactly one stream must match; none is retried with back-off, with the
streams found in the log; bad or missing channel meta-data is one error
naming the channels. Needs `pip install 'hmdrt[lsl]'`, as do the emulator and
`[lsl]`.""",
    "convert": """\
Converts a trace between the formats `replay://` reads and the two hmdrt writes, or exports it to BIDS
(`docs/protocols.md`, Replay formats): the output format follows OUT's name. `.jsonl` / `.jsonl.gz`: the native
trace, every sample as read. `.csv` / `.csv.gz`: hmdrt CSV (`replay/formats/generic_csv.py`), gaze only, which reads
back with the same times, validity and directions. `NAME_physio.tsv.gz`: BIDS eye-tracking physiological recordings
(`replay/bids.py`), one `NAME_recording-eyeN_physio.tsv.gz` and `.json` per eye, yaw and pitch in degrees
("eye-in-head"). It prints what it wrote and how many head-pose samples a gaze-only format left out. An unknown
output name, an option the input's format does not take, or an output that exists without `--force` is refused
in one line, and nothing is written.""",
    "ctl": """\
`hmdrt ctl` checks the command against the declarations of the [control socket](#control-socket)'s commands
before it sends anything, so a bad one is refused with the one line the control socket and the live page give.
It prints the reply as JSON (`ok` when there is nothing but the `"ok"`) and exits 0, or prints the refusal as
`hmdrt: error: ...` and exits 1.""",
    "watch": """\
It prints `hmdrt watch: http://127.0.0.1:PORT/?token=TOKEN (read-only:
http://127.0.0.1:PORT/)` once it serves and runs until SIGINT or SIGTERM (the
compositor runs on). The server (`hmdrt/watch/`) answers:

| Request | Does | Needs |
|---|---|---|
| `GET /` | the page (`hmdrt/watch/static/`: plain HTML and JS, uPlot vendored) | - |
| `GET /static/NAME` | the page's script, styles and uPlot | - |
| `GET /ws` | a websocket: the page's feed and its commands | the token for commands that change the compositor |
| `GET /api/state` | JSON: the compositor's status, the run report so far, each driver's state, gaze and pose \
rates, counts and clock, and the server's refusal counts | - |
| `POST /api/command` | a command (below) as a JSON body; the compositor's reply | the token |

Each needs a `Host` header naming the server (the bound address, `localhost`,
`127.0.0.1`, `[::1]` or an `--allow-host` name, with its port) and, if it has an
`Origin` header, this same origin; otherwise it is answered 403 and counted. The
token goes in the query (`?token=`) or in an `X-Hmdrt-Token` header; a wrong one
is refused wherever it is given. Bound beyond loopback, every request but
`/static/` needs it.

Commands, on the websocket or `POST /api/command`, are the control socket's
(see [Control socket](#control-socket)) as JSON objects of at most 4096 bytes,
e.g. `{"cmd": "set", "method": "rrm?fovea_deg=5"}`, `{"cmd": "set", "params":
{"fovea_deg": 5}}`, `{"cmd": "snapshot"}` or `{"cmd": "shutdown"}`, each with
an optional numeric `"id"` that the reply repeats. They are checked by the same
declarations as on the control socket, so a bad one is refused (and counted)
with the control socket's message before anything reaches the compositor; the
others are forwarded as they are. The websocket sends JSON
text messages with a `type`: `hello` (whether this page holds the token, the
methods and their parameters), `frames` (batches of frame points, 20 a second at
most), `stats` (the run report, each second), `status` (each second: the
compositor's status, the drivers, whether its control socket would take
commands from this server and why not, the server's refusals), `log` and `reply`;
and each preview as a binary message: a 4-byte big-endian length, a JSON header
(`vsync`, `frame_id`, `method`, `fovea_deg`, `width`, `height`, `scale`, and per
eye `x0`, `width`, `gaze` and `fovea` in preview pixels), then the JPEG.""",
    "eval": "`--cluster` and `--resume`: [docs/cluster.md](cluster.md).",
    "export perfetto": """\
A timeline of the run in Chrome's trace-event JSON (`hmdrt/telemetry/perfetto.py`), for ui.perfetto.dev or
chrome://tracing: one process with the tracks `render` (a span per rendered frame, wake-up to hand-over, the
method's stages nested in it), `display` (each VSync as an instant, the latch or timewarp as a span, a
process-wide instant per deadline miss), `gaze samples` and `pose samples` (each sample a frame used, at its
host capture time). Times are microseconds of the run's clock; each span's args carry the record's predicted
and actual times, parameters and measured ms. In virtual time a frame's span is its work's wall time, at most a
period, with its stages shrunk in proportion (`stages_scaled`); a span cut to fit its parent says `cut`.""",
    "report plot": """\
From a frames log (a `.jsonl` file): `timeline.png` (each rendered frame's `frame_ms` and `render_ms` per
VSync against the period and the deadline, the period less `[pacing] margin_ms`; late frames and repeats
marked; the controller's level below) and `latency.png` (gaze- and pose-to-photon histograms with p50, p99 and
the period's multiples; samples held through a blink or lost tracking left out). From a run report (any other
file): `summary.png` (frame time and latency percentiles, the controller's trajectory) and a note that the rest
needs a frames log.

Both commands read at most 1 GiB of frames log (64 KiB a line) or 64 MiB of report. A line that is not a frame
record, out of VSync order or with an impossible value is a one-line error naming the file and line; only a
last line cut short (a run killed mid-write) is left out, with a warning.""",
}

CONTROL_BEFORE = """\
`hmdrt status` and `hmdrt ctl` ask the control socket. Other clients send a msgpack map
`{"cmd": NAME, ...}` to it (ZeroMQ REQ) and get a map with `"ok"`. The commands
are declared once, in `hmdrt/compositor/commands.py`, and the control socket
(`hmdrt/compositor/control.py`), the live page and `hmdrt ctl` check a request
against them: anything else gets `"ok": false` and one line naming the problem,
the same from each."""

CONTROL_AFTER = """\
The commands marked as changing the compositor may, with `[security]`, be sent
only by an authenticated client, and on a `tcp://` control socket without
`[security]` by none (`status` and `stats` answer). A snapshot name
is letters, digits, `.`, `_` and `-` ending in `.png`, without `..` and not
starting with `.`; a path, another name or an existing file is refused and
counted (`security.snapshots_refused`). One client (a process on `ipc://`,
an address on `tcp://`, a key with CURVE) may send 100 requests a second, 200
at once; more get `"rate limited"` and are counted (`rate_limited.control`).
SIGHUP makes the daemon re-read its config file between frames (see
[Reload](#reload))."""

RUN_CONFIG = """\
## Run config

`hmdrt run CONFIG.toml` reads a TOML file into `RunConfig`
(`hmdrt/compositor/config.py`). Every key is optional. Unknown keys and bad
values are errors, all reported in one line. Paths in the file (a `replay://`
trace, `hid://stub`'s `trace=`, the report, the frames folder, the video, the
key files) are relative to the config file, so a config runs the same from
any working directory. `configs/default.toml` is a complete example that runs
on a fresh machine: `hmdrt run configs/default.toml`."""

# run config: a section's prose before its table, then after it, by section name ("": the top level)
RUN_SECTIONS = {
    "drivers": (
        "An array of tables, one per driver the compositor starts itself.",
        "Drivers can also run in their own processes (`hmdrt driver URL`) and publish\nto the ingest endpoint.",
    ),
    "bus": (
        "",
        """\
By default each socket is a Unix socket of this user's alone, in
`$XDG_RUNTIME_DIR/hmdrt/` (else `/tmp/hmdrt-UID/`), created 0700 (an existing
one must be yours, closed to group and others, and no link); the sockets are
made 0600 and removed on exit. A configured `ipc://` path must be in such a
folder too; an abstract one (`ipc://@NAME`) is refused. An endpoint ending in
`:*` binds a free port. Without `[security]` every endpoint must be loopback,
and a `tcp://` one is open to every local user: the start says so in the log
and the report (`security.open_to_local_users`), and a `tcp://` control
socket only reads (docs/runtime.md, "Access").""",
    ),
    "security": (
        """\
Absent by default: every socket binds loopback, and the default sockets are
this user's alone (see [bus]). When present, all three sockets use CURVE
(docs/runtime.md, "Access").""",
        "",
    ),
    "fallback": ("When the gaze device goes silent (`hmdrt/compositor/fallback.py`).", ""),
    "controller": ("The budget controller (`hmdrt/compositor/controller.py`).", ""),
    "output": (
        "",
        """\
The frames, the video and the frames log are written on threads of their own. In real time they never hold up
the display: what finds a writer's queue full is dropped and counted in the report (`frames_not_written`,
`frames_log_not_written`). In virtual time the display waits for them instead, so every frame is written and two
runs of a config write the same files (the log differs only in its wall-clock times: `frame_ms`, `render_ms`,
`present_ms`, `overhead_ms`, `stages_ms`).""",
    ),
    "lsl": (
        "",
        """\
Both stamp each sample with its photon time (the VSync it was presented at) on
the LSL clock, so LabRecorder records them beside EEG (`docs/protocols.md`,
section 9.5, lists the channels). They are pushed from a thread of their own:
in real time a record that finds the queue full is dropped and counted
(`lsl_not_pushed` in the report); in virtual time the display waits. Needs
`pip install 'hmdrt[lsl]'`; changing it needs a restart.""",
    ),
    "run": (
        "",
        "`hmdrt run --frames`, `--duration` and `--virtual-time` override `frames`,\n`duration_s` and `virtual_time`.",
    ),
}

RELOAD = """\
### Reload

On SIGHUP the daemon re-reads its config between frames; the bus stays up.
`scene`, `[display]`, `[[drivers]]`, `[bus]`, `[security]` and `[lsl]` need a restart,
as do `output.video` and `output.every` while a video is written, and
`output.frames_log` (the open log goes on); `[run]` (seed, threads, limits)
stays as it runs. The daemon publishes a `log` message
naming what needs a restart (`hmdrt.compositor.config.reload_plan`)."""

EVAL_CONFIG = """\
## Eval config

`hmdrt eval CONFIG.toml --out DIR` reads `EvalConfig`
(`hmdrt/evaluate/config.py`). Every cell of scenes x profiles x traces x
method cells is rendered and scored against the ground truth. Paths are
relative to the config file. `configs/eval/quick.toml` is the example to run
first; `configs/eval/paper_tables.toml` and `configs/eval/speedup.toml` are
others. On Dask distributed (`--cluster`), across machines, see
[docs/cluster.md](cluster.md)."""

EVAL_SECTIONS = {
    "": ("", "Scenes, profiles, traces and methods each need at least one entry."),
    "traces": ("What the eye and head do. Exactly one of `gaze`, `path`, `builtin` per trace.", ""),
    "methods": (
        "",
        """\
Every method spec and every `compare_to` is checked before anything is rendered.

The summary names, per scene, profile, trace and baseline, the fastest foveated cell compared with that baseline
whose foveal PSNR is at least the baseline's, with its speed-up and foveal PSNR delta. Flicker is the mean
absolute difference between a cell's frame-to-frame change and the truth's: 0 when the images change as the
truth does, more for an image that changes where the truth does not or stays where it moves.""",
    ),
}

NOT_IN_FILES = ("source",)  # set on load, not read from the file

RUN_MEANINGS = {
    "scene": "a built-in scene (`whitted`, `tunnel_maps`, `tunnel_geom`, `voxel_city`, `shooting_range`, "
    "`interior`, `bunny`; with options, e.g. `voxel_city?size=50`), a scene `.toml` or a mesh file",
    "display.profile": "a built-in HMD profile (`dk2`, `rift_s`, `fove0`, `vive_pro_eye`, `sim-cpu`, `sim-cpu-640`) "
    "or a profile `.toml`; its refresh rate sets the VSync",
    "display.eyes": "which eyes are rendered",
    "display.resolution": "per-eye `WIDTHxHEIGHT` overriding the profile's, same field of view",
    "display.refresh_hz": "the VSync rate; 0 uses the profile's",
    "method.name": 'a method, with options as in `"weier16?frc=small"`: `full`, `regular`, `rrm`, `kim21`, '
    "`weier16`, `weier18`",
    "method.options": "more options, as a table; `docs/methods.md` lists each method's",
    "drivers.url": "a driver URL, as `hmdrt driver URL` takes (`docs/protocols.md`)",
    "bus.ingest": 'the SUB socket drivers publish to; `""`: `ipc://$XDG_RUNTIME_DIR/hmdrt/ingest-PID.sock`',
    "bus.telemetry": 'the PUB socket of `frame`, `stats` and `log`; `""`: `.../telemetry-PID.sock`',
    "bus.control": 'the socket of the control commands; `""`: `.../control-PID.sock`',
    "security.server_key": "the compositor's secret key file, `NAME.key_secret` (from `hmdrt keys`)",
    "security.allowed_clients": "the public key files (`NAME.key`) of the clients allowed",
    "pacing.margin_ms": "fixed margin before the VSync",
    "pacing.present_to_display_ms": "from present to the predicted display time; -1 means half the period",
    "pacing.render_delay_ms": "extra time added to every render, to see how misses are handled",
    "pacing.tail_quantile": "the wake-up plans for this quantile of the last `tail_window` render times "
    "(0: the filtered mean only, as Monado)",
    "pacing.tail_window": "render times the quantile is taken over",
    "prediction.horizon_ms": "gaze and pose are extrapolated at most this far past the newest sample",
    "prediction.gaze_device": 'the device whose gaze drives the frames; `""`: the one with the newest gaze',
    "prediction.pose_device": "the same for head pose",
    "gaze.saccade_prediction": "at a saccade, predict its flight and landing point from its velocity profile and "
    "the main sequence, and while a prediction stands show frames along it instead of extrapolating the gaze "
    "velocity (`hmdrt/tracking/saccade.py`, docs/trackers.md)",
    "fallback.stale_ms": "silent this long: an outage begins",
    "fallback.widen_deg_per_s": "then the fovea widens this fast",
    "fallback.max_widen_deg": "up to this much",
    "fallback.centre_after_ms": "then the gaze falls back to the screen centre; must not be below `stale_ms`",
    "controller.kind": "`hold-budget` keeps the deadline-miss rate under its target by lowering the method's "
    "quality; `none` leaves it",
    "controller.target_miss_rate": "the deadline-miss rate to stay under",
    "controller.headroom": "the fraction of the budget the render time aims at",
    "controller.widen_latency_ms": "widen the fovea by gaze speed times this tracker latency",
    "controller.accuracy_deg": "and by this tracker accuracy",
    "controller.foresight": "pick each frame's quality from its predicted render time: a probe of the fovea where "
    "the gaze is about to be and a model of the rest of the frame (docs/runtime.md); `false`: by feedback alone",
    "output.report": 'the run report JSON (`""`: none, unless `--report`)',
    "output.frames_dir": 'a folder for the presented frames as PNG (`""`: none)',
    "output.video": 'the presented frames as an H.264 video at refresh / `every` fps (`""`: none; needs the '
    "`video` extra)",
    "output.every": "write every Nth VSync to `frames_dir` and `video`",
    "output.snapshot_dir": 'the folder control `snapshot` writes into, by file name (`""`: the folder `hmdrt run` '
    "started in)",
    "output.frames_log": "every VSync's frame record as JSON Lines after a header line, a new file each run "
    '(`""`: none; `hmdrt run --frames-log` overrides): each line written whole as the frame is shown, so a killed '
    "run keeps its frames; read by `hmdrt export perfetto` and `hmdrt report plot`",
    "lsl.outlets": 'Lab Streaming Layer outlets of what was shown: `"frames"`, a JSON marker per VSync (frame id, '
    'new/late/repeat, missed, method); `"samples"`, each rendered frame\'s gaze, head pose, their capture times and '
    "predictions, and gaze- and pose-to-photon latency",
    "run.seed": "seed of every stochastic step",
    "run.threads": "tracing threads (0: all cores)",
    "run.kernel_threads": "numba threads of the per-pixel kernels of the render and display threads (0: all cores; "
    "`auto`: 1 on a machine of 2 cores or fewer, where a parallel kernel waits for a core that the display, ingest "
    "and drivers want, else all)",
    "run.virtual_time": "a simulated clock, one period per frame; the run reproduces bit for bit",
    "run.frames": "stop after this many VSyncs (0: until stopped)",
    "run.duration_s": "or after this long (0: until stopped)",
    "run.warmup_s": "the report also gives the miss rate after this",
}

EVAL_MEANINGS = {
    "scenes": "scenes to render",
    "profiles": "HMD profiles",
    "resolution": "per-eye `WIDTHxHEIGHT` overriding every profile's, same field of view",
    "eye": "the eye rendered",
    "frames": "frames per cell (`--frames` overrides); `frames - warmup_frames` of them are timed and scored",
    "warmup_frames": "frames rendered before timing, neither timed nor scored; fewer than `frames` "
    "(`--warmup-frames` overrides). A method that needs a longer history (its `warmup_frames`: RRM's refresh "
    "cycle N) lengthens the warm-up of its scene, profile and trace to that; methods without history (`full`, "
    "`regular`) skip it",
    "timing_rounds": "the frames are rendered this many times for their times, the first round scored, the others "
    "from fresh methods; `ms_per_frame` is the median of the rounds' means, and a speed-up spreading over more "
    "than 15% across them is marked `timing_noisy` (docs/evaluation.md, Timing on a busy machine)",
    "truth_spp": "the ground truth: `regular` at this many samples per pixel",
    "seed": "seed",
    "threads": "tracing threads (0: all cores; with `--cluster`, 0 means one per task)",
    "cache_dir": 'where ground truths are cached (`""`: `$XDG_CACHE_HOME/hmdrt/truth`, else '
    "`~/.cache/hmdrt/truth`); with `--cluster`, a folder named here must be one every worker sees (docs/cluster.md)",
    "jod": "FovVideoVDP's foveated JOD per cell, in its video mode: the scored frames as one video at the profile's "
    "refresh rate, the fixation following each frame's gaze (needs the `eval` extra)",
    "tables": "the tables to fill in tables.md: the papers' (`weier2016`, `kim2021`, `smith2013`, `weier2018`) "
    "and `latency`",
    "crop_px": "side of the crops at the gaze point",
    "score_space": "PSNR, SSIM and flicker of display-encoded images (`srgb`: the sRGB transfer function, "
    "unquantised, as a display shows them) or of `linear` radiance; both clipped to [0, 1]. Results, tables and "
    "plots name it",
    "traces.name": "label in tables and plots",
    "traces.gaze": 'a fixed gaze `"YAW,PITCH"` in degrees, head still',
    "traces.path": "a gaze/pose trace (native JSONL, CSV, EyeLink ASC)",
    "traces.builtin": "the built-in path: head sway with fixations and saccades",
    "traces.group": "traces of one group are averaged in the papers' tables (smith2013: every fovea position); "
    '`""`: the trace\'s own label',
    "traces.latency_ms": "the method renders each frame with the gaze the tracker reported this long before the "
    "frame's photon time; the scores follow the true gaze",
    "traces.tracker": "what the tracker gets wrong: a preset (`perfect`, `eyelink-1000-plus`, `pupil-core`, "
    "`tobii-pro-spectrum`, `htc-vive-pro-eye`, `varjo-xr-3`, `fove-0`) or a table of `accuracy_deg`, "
    "`precision_deg` (RMS sample to sample), `rate_hz`, `loss_rate` (the fraction of samples lost) and `loss_ms` "
    "(each dropout's length); docs/trackers.md",
    "traces.pose_latency_ms": "the method renders each frame from the head pose the head tracker reported this "
    "long before the frame's photon time; the ground truths stay at the true pose",
    "traces.pose_tracker": "what the head tracker gets wrong: a preset (`perfect`, `htc-vive`) or a table of "
    "`position_mm` and `orientation_deg` (RMS sample to sample, white noise) and `rate_hz`; docs/trackers.md",
    "traces.prediction": "of the gaze and the head pose alike: `off`: the newest sample that has arrived; "
    "`default`: carried on to the photon time as the compositor's SampleStore predicts with the run config's "
    "default `[prediction]`; `saccade`: that, and along a predicted saccade's flight to its landing point, as with "
    "`[gaze] saccade_prediction`",
    "traces.sweep": "several values of `latency_ms`, `tracker`, `pose_latency_ms`, `pose_tracker` or `prediction`: "
    "the entry stands for one trace per combination (`[traces.sweep]`, `latency_ms = [0, 20, 50]`)",
    "methods.name": 'a method, with options as in `"weier16?frc=small"`',
    "methods.options": "fixed options; a list is the value of an option of several values (kim21's alpha at its "
    "six band edges: `alpha = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]`)",
    "methods.sweep": "option -> list of values; one cell per combination (at most 10 000 cells)",
    "methods.label": "names the cells in tables and plots; a sweep's cells add their values",
    "methods.scenes": "only on these of the config's scenes (`[]`: all)",
    "methods.traces": "only on these of the config's traces, by label or group (`[]`: all)",
    "methods.compare_to": 'the label of the cell these cells are compared with (`""`: `full`): each row\'s '
    "`baseline`, `speedup_vs_baseline` and `psnr_fovea_vs_baseline` (dB), the summary and kim2021's table. It must "
    "name exactly one cell on every scene and trace the entry runs on: an unlabelled cell's label is its method "
    "spec, a sweep's cells add their values to the label",
}
