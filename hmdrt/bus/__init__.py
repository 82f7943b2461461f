"""The ZeroMQ bus: message schema and framing (docs/architecture.md, "Bus").

The compositor's ingest, telemetry and control sockets bind ipc:// in a folder of this user's only by default
(hmdrt.bus.local); hmdrt.bus.security guards any other binding and hmdrt.bus.limits bounds what one client may take.
"""
