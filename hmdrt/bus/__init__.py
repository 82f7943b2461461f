"""The ZeroMQ bus: message schema and framing (docs/architecture.md, "Bus")."""

INGEST = "tcp://127.0.0.1:5560"  # the compositor's SUB; drivers connect their PUB here
TELEMETRY = "tcp://127.0.0.1:5561"
# the control REP binds ipc:// in a folder of this user's only by default: hmdrt.bus.local
