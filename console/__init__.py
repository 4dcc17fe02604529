"""The operator console: a web page served by visionpos itself (docs/console.md).

    settings.py  the `console:` section (bind, port, max_clients, update_rate_hz, token)
    view.py      what the page shows, read from a running server or a replay (scene, live state)
    health.py    the health view and /api/health, with warnings in words
    server.py    aiohttp HTTP + WebSocket server on the fusion server's own loop
    replay.py    a recording replayed at the console's speed (`visionpos replay LOG --view`)
    static/      the page (HTML, JS, CSS) and three.js, vendored (static/vendor/VENDOR.md)

An edge like bridge/ and stations/: it uses the core only; visionpos.app composes it.
"""
