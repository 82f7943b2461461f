"""`hmdrt watch`: a live view of a running compositor in the browser (README "Watching a run").

server (the aiohttp application and `hmdrt watch`), access (Host, Origin and token checks), link (the compositor's
telemetry and control socket), hub (what the open pages are sent), protocol (the page's messages), static/ (the
page). The previews it shows are made in the compositor by hmdrt.compositor.preview.
"""
