"""The console's HTTP and WebSocket server (aiohttp), on the fusion server's own asyncio loop.

    GET /                the page (static/index.html), its scripts and three.js (static/, vendored)
    GET /api/health      health as JSON (console/health.py)
    GET /api/scene       cameras and bodies (console/view.py scene)
    GET /ws              WebSocket: {"type": "scene"} once, then {"type": "state"} at update_rate_hz (the
                         camera views in every second one),
                         {"type": "health"} once a second, {"type": "replay"} in a replay, {"type": "calib"}
                         when the calibration assistant's counts or solve changed; the client
                         may send {"cmd": ...}: "rays" (a camera's blob rays), "views" (on: false while the
                         tab is hidden: no camera views for it), "health", replay controls (console/replay.py),
                         "solve" (the wand solve: console/calibration.py), "wave", "apply_calibration",
                         "ground" and "apply_ground" (a running fusion server's: console/live_calibration.py; an
                         apply sends every tab the new scene), "record" (start or stop a
                         recording: console/recording.py; answered to every tab as {"type": "record"}),
                         "write_pose" (the camera monitor's corrected pose into the arena file: console/arena_file.py),
                         "still" and "mask" (a station's still image, its mask saved back: console/stills.py);
                         a refused message (bad JSON, an unknown command or camera, a mask outside the image,
                         over MAX_MESSAGE_BYTES, a tab over console.max_clients) changes nothing and is
                         answered to its sender alone: {"type": "error", "error": "why"} (error_text)

One update task: once per tick it builds the state (only when a client is connected), encodes it
ONCE (a camera's view only when that camera sent something new: console/view.py) and puts the text
in each client's queue of QUEUE_UPDATES; a full queue drops its oldest
update (counted), so a slow or stalled browser loses updates and never holds up fusion or the
other clients. Each client's sender task awaits the socket; nothing else does.

Access, checked before any handler runs (the middleware `_access`):
- the Host header must name the console itself (`allowed_hosts`: 127.0.0.1, localhost, [::1], the bind
  address, the address the connection came in on, `console.hosts`, each with the console's port; a loopback
  name with any port: an SSH tunnel), else 403: a page of another site whose name is rebound to this host's
  address (DNS rebinding) sends its own name;
- an Origin header, where a browser sends one, must be one of those hosts or the request's own, and a browser's
  Sec-Fetch-Site must say same-origin (or a navigation), else 403 (a page from elsewhere must not drive or
  read the console through the operator's browser);
- bound to loopback no token is needed; bound elsewhere every request must carry the token (`?token=`, an
  `Authorization: Bearer` header, or the cookie the page gets with its first request), else 401.
Bad requests and messages are answered or dropped and logged once per cause (RateLimitedLog).
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import time
from pathlib import Path
from typing import Any, Awaitable, Callable
from urllib.parse import urlsplit

from aiohttp import WSCloseCode, WSMsgType, web

from console.arena_file import write_monitored_pose
from console.health import HealthView
from console.recording import ConsoleRecorder
from console.settings import ConsoleSettings
from console.stills import StationCommands
from console.view import ConsoleView, scene
from visionpos.logutil import RateLimitedLog

log = logging.getLogger(__name__)
# the updates are trees of plain values: the encoder's cycle check only costs time (a quarter of the encoding)
_encode = json.JSONEncoder(check_circular=False).encode

STATIC = Path(__file__).with_name("static")
QUEUE_UPDATES = 2  # per client: updates waiting to be sent; more drop the oldest
HEALTH_PERIOD_S = 1.0  # the health table and /api/health's rates: once a second, as the status lines
WATCH_PERIOD_S = 0.5  # the residual and static-blob watches run this often, with or without clients
MAX_MESSAGE_BYTES = 4096  # from a client: commands are small
COOKIE = "visionpos_console"
LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})
CONTENT_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".txt": "text/plain",
                 ".png": "image/png"}


def error_text(message: str) -> str:
    """A refusal as sent to the one client it concerns: {"type": "error", "error": message} (docs/console.md)."""
    return json.dumps({"type": "error", "error": message})


CALIBRATION_COMMANDS = ("solve", "wave", "apply_calibration", "ground", "apply_ground")
TOO_BIG = f"message refused: over {MAX_MESSAGE_BYTES} bytes (a command is a short JSON object); connection closed"


class _Socket(web.WebSocketResponse):
    """A console WebSocket: a message over its max_msg_size, which aiohttp answers by closing (1009), gets the
    refusal as a message first, so the page can say why."""

    async def close(self, *, code: int = WSCloseCode.OK, message: bytes = b"", drain: bool = True) -> bool:
        if code == WSCloseCode.MESSAGE_TOO_BIG and not self.closed:
            try:
                await self.send_str(error_text(TOO_BIG))
            except (ConnectionError, RuntimeError):
                pass
            message = message or b"message too big"
        return await super().close(code=code, message=message, drain=drain)


class Client:
    """One connected browser tab: its socket, its bounded queue of encoded updates, its counters."""

    def __init__(self, ws: web.WebSocketResponse, peer: str):
        self.ws = ws
        self.peer = peer
        self.queue: asyncio.Queue[str] = asyncio.Queue(QUEUE_UPDATES)
        self.sent = 0
        self.dropped = 0
        self.dropped_at_calib = 0  # its `dropped` when it was last offered the calibration state
        self.rays: int | None = None  # the camera whose blob rays this tab draws
        self.views = True  # it shows the camera views (a hidden tab says no: none are built for it)

    def offer(self, text: str) -> None:
        """Queue one update; a full queue loses its oldest (the browser is behind)."""
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(text)


def _offer_calib(client: Client, text: str) -> None:
    """The calibration state to one tab, remembering its drops so far (the health tick offers it again only to
    a tab that dropped something since)."""
    client.offer(text)
    client.dropped_at_calib = client.dropped


class ConsoleServer:
    """The console for `source` (a FusionServer or a replay session; see console/view.py).

    controls: optional async callable(dict) -> dict | None for {"cmd": ...} messages (a replay's
    play/pause/seek/speed); without it such messages are answered with an error.
    extra: optional callable() -> dict merged into every state message (the replay's position).
    masks: camera id -> {"rois", "ignore", "mask_png"} (visionpos.app.console.station_masks), shown in the views.
    calibration: optional console.calibration.CalibrationAssistant: its state goes to every client when it
    changes, and it answers "solve".
    """

    def __init__(self, settings: ConsoleSettings, source: Any, clock: Callable[[], int] = time.monotonic_ns,
                 controls: Callable[[dict[str, Any]], Awaitable[dict[str, Any] | None]] | None = None,
                 extra: Callable[[], dict[str, Any]] | None = None, masks: dict[int, dict[str, Any]] | None = None,
                 calibration: Any = None):
        self.settings = settings
        self.source = source
        self.clock = clock
        self.controls = controls
        self.extra = extra
        self.calibration = calibration
        self._calib_version = -1
        self.view = ConsoleView(source)
        for cam in self.view.scene["cameras"]:
            cam["mask"] = (masks or {}).get(cam["id"])
        self.view.scene["update_rate_hz"] = settings.update_rate_hz  # the page compares its own rate with it
        self.recording = ConsoleRecorder(source, settings.record_dir)
        self.view.scene["can_record"] = self.recording.available  # the page shows the record button
        self.health_view = HealthView(self.view)
        self.clients: set[Client] = set()
        self.rlog = RateLimitedLog(log)
        self.counters = {"updates": 0, "refused_host": 0, "refused_token": 0, "refused_origin": 0, "refused_full": 0,
                         "bad_messages": 0, "send_errors": 0, "update_errors": 0, "dropped_by_gone": 0}
        self.cpu_ns = 0  # CPU time of the update task's work and of the sends (the loop's thread), for the bench
        self.port: int | None = None
        self._scene_text = json.dumps(self.view.scene)
        self._runner: web.AppRunner | None = None
        self._task: asyncio.Task | None = None
        self._senders: set[asyncio.Task] = set()
        self._watch_due = False
        self._camera_share = min(settings.camera_view_rate_hz / settings.update_rate_hz, 1.0)
        self._camera_credit = 1.0  # the first update carries them
        self.stations = StationCommands(self)

    def scene_changed(self) -> None:
        """The scene (a camera's mask) changed: tabs that connect from now on get the new one."""
        self._scene_text = json.dumps(self.view.scene)

    # ---------------------------------------------------------------- lifecycle

    @property
    def address(self) -> str:
        """The console's address without its token: what logs may hold."""
        host = self.settings.bind if self.settings.bind not in ("0.0.0.0", "::") else "127.0.0.1"
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The address to print on the operator's terminal (visionpos/app/console.py), never to log: with the
        token only where it was made at start (the one way to learn it); a configured one is never printed."""
        return self.address + (f"?token={self.settings.token}" if self.settings.token_generated else "")

    async def start(self) -> None:
        app = web.Application(middlewares=[self._access], client_max_size=MAX_MESSAGE_BYTES)
        app.router.add_get("/", self._index)
        app.router.add_get("/api/health", self._health)
        app.router.add_get("/api/scene", self._scene)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/static/{path:.+}", self._static)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.settings.bind, self.settings.port)
        await site.start()
        self.port = self._runner.addresses[0][1]
        self._task = asyncio.get_running_loop().create_task(self._update_loop(), name="visionpos-console")
        if self.calibration is not None:
            self.calibration.start()
        log.info("console on %s%s", self.address, " (token required)" if self.settings.token else "")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self._task = None
        if self.calibration is not None:
            await self.calibration.stop()
        for c in list(self.clients):
            await c.ws.close()
        for t in list(self._senders):
            t.cancel()
        self.stations.cancel()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def stats(self) -> dict[str, Any]:
        return {**self.counters, "clients": len(self.clients),
                "dropped": self.counters["dropped_by_gone"] + sum(c.dropped for c in self.clients),
                "log_suppressed": self.rlog.suppressed}

    # ---------------------------------------------------------------- access

    def allowed_hosts(self, local_addr: str | None = None) -> frozenset[str]:
        """The Host values (lower case) that name this console: loopback names, the bind address, local_addr (the
        address a connection came in on: what a browser on another computer typed for a console on 0.0.0.0) and
        console.hosts, each with the console's port (and without it on port 80, as browsers send it)."""
        names = {*LOOPBACK_NAMES, *self.settings.hosts}
        for addr in (self.settings.bind, local_addr):
            if addr:
                ip = ipaddress.ip_address(addr.split("%", 1)[0])
                ip = getattr(ip, "ipv4_mapped", None) or ip  # ::ffff:a.b.c.d on a dual-stack socket
                if not ip.is_unspecified:
                    names.add(str(ip))
        out = set()
        for n in names:
            n = f"[{n}]" if ":" in n else n.lower()
            out.add(f"{n}:{self.port}")
            if self.port == 80:
                out.add(n)
        return frozenset(out)

    def _foreign(self, request: web.Request) -> str | None:
        """"host" or "origin" when the request's Host, or its Origin where it has one, is not this console."""
        host = (request.headers.get("Host") or "").lower()
        sock = request.transport.get_extra_info("sockname") if request.transport is not None else None
        allowed = self.allowed_hosts(sock[0] if sock else None)
        # a loopback name on another port: an SSH tunnel's local end (ssh -L 9000:127.0.0.1:8080); no page of
        # another site can send it (its own name is what DNS rebinding sends)
        try:
            tunnel = urlsplit(f"//{host}").hostname in LOOPBACK_NAMES
            origin = request.headers.get("Origin")
            origin_netloc = None if origin is None else urlsplit(origin).netloc.lower()
        except ValueError:  # e.g. an unclosed [ of an IPv6 address
            return "host"
        if host not in allowed and not tunnel:
            return "host"
        if origin_netloc is not None and origin_netloc not in allowed | {host}:
            return "origin"
        # a browser's fetch metadata: a page of another origin fetching without CORS sends no Origin, but says
        # where it comes from; only a navigation (a link, a typed URL) may come from elsewhere
        site = request.headers.get("Sec-Fetch-Site", "same-origin")
        if site not in ("same-origin", "none") and request.headers.get("Sec-Fetch-Mode") != "navigate":
            return "origin"
        return None

    def _token_ok(self, request: web.Request) -> bool:
        token = self.settings.token
        if token is None:
            return True
        given = request.query.get("token") or request.cookies.get(COOKIE) or ""
        auth = request.headers.get("Authorization", "")
        if not given and auth.startswith("Bearer "):
            given = auth[7:]
        return hmac.compare_digest(given.encode("utf-8", "replace"), token.encode())

    @web.middleware
    async def _access(self, request: web.Request, handler: Any) -> web.StreamResponse:
        foreign = self._foreign(request)
        if foreign is not None:
            self.counters[f"refused_{foreign}"] += 1
            self.rlog.log(foreign, logging.WARNING, "console: refused %s %s from %s: Host %r / Origin %r is not this "
                          "console (a page of another site?)", request.method, request.path, request.remote,
                          request.headers.get("Host"), request.headers.get("Origin"))
            return web.Response(status=403, text=f"visionpos console: refused: the {foreign.capitalize()} of this "
                                                 "request is not this console's address (open it as "
                                                 f"http://127.0.0.1:{self.port}/, this host's IP address, or a "
                                                 "name listed in console.hosts)\n")
        if not self._token_ok(request):
            self.counters["refused_token"] += 1
            self.rlog.log("token", logging.WARNING,
                          "console: refused %s %s from %s: missing or wrong token", request.method, request.path,
                          request.remote)
            return web.Response(status=401, text="visionpos console: this address needs the token printed at "
                                                 "start: open the URL with ?token=...\n")
        resp = await handler(request)
        if self.settings.token is not None and request.query.get("token") and not resp.prepared:
            resp.set_cookie(COOKIE, self.settings.token, httponly=True, samesite="Strict")
        return resp

    # ---------------------------------------------------------------- HTTP

    async def _index(self, request: web.Request) -> web.Response:
        # the address opened from the terminal (?token=): the cookie now holds the token, and the page is shown
        # at "/" so the address bar, a screenshot or a shared link does not carry it. Only where the browser says
        # the navigation is its own (typed, a bookmark) or the console's: a SameSite=Strict cookie set on the
        # way from another site's link would not come back with the redirect
        if (self.settings.token is not None and request.query.get("token")
                and request.headers.get("Sec-Fetch-Site") in ("none", "same-origin")):
            return web.Response(status=303, headers={"Location": "/", "Cache-Control": "no-store"})
        return web.Response(body=(STATIC / "index.html").read_bytes(), content_type="text/html",
                            headers={"Cache-Control": "no-store"})

    async def _static(self, request: web.Request) -> web.Response:
        rel = request.match_info["path"]
        path = (STATIC / rel).resolve()
        if not path.is_file() or STATIC.resolve() not in path.parents:
            return web.Response(status=404, text="not found\n")
        kind = CONTENT_TYPES.get(path.suffix, "application/octet-stream")
        return web.Response(body=path.read_bytes(), content_type=kind)

    async def _health(self, request: web.Request) -> web.Response:
        h = self.health()
        return web.Response(text=json.dumps(h), content_type="application/json")

    async def _scene(self, request: web.Request) -> web.Response:
        return web.Response(text=self._scene_text, content_type="application/json")

    def health(self) -> dict[str, Any]:
        h = self.health_view.health(self.clock())
        h["console"] = self.stats()
        h["recording"] = self.recording.state()
        return h

    # ---------------------------------------------------------------- WebSocket

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        # no per-message compression: it would cost the loop CPU for every client and update
        ws = _Socket(max_msg_size=MAX_MESSAGE_BYTES, heartbeat=10.0, compress=False)
        await ws.prepare(request)
        if len(self.clients) >= self.settings.max_clients:  # answered on the socket: a page cannot read an HTTP 503
            self.counters["refused_full"] += 1
            self.rlog.log("full", logging.WARNING, "console: refused a client from %s: %d connected "
                          "(console.max_clients)", request.remote, len(self.clients))
            n = self.settings.max_clients
            await ws.send_str(error_text(f"refused: this console serves at most {n} tabs at once and {n} are open "
                                         "(console.max_clients); close one, this tab retries"))
            await ws.close(code=WSCloseCode.TRY_AGAIN_LATER, message=b"console full")
            return ws
        client = Client(ws, str(request.remote))
        self.clients.add(client)
        sender = asyncio.get_running_loop().create_task(self._sender(client))
        self._senders.add(sender)
        try:
            await ws.send_str(self._scene_text)
            client.offer(json.dumps({"type": "health", "health": self.health()}))
            if self.calibration is not None:
                _offer_calib(client, self._calib_text())
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._command(client, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    await self._bad(client, "binary", "binary messages are not understood; send JSON text")
                elif msg.type == WSMsgType.ERROR:
                    if getattr(msg.data, "code", None) == WSCloseCode.MESSAGE_TOO_BIG:  # answered by _Socket
                        self.counters["bad_messages"] += 1
                    self.rlog.log(("wserror", client.peer), logging.INFO, "console: client %s: %s", client.peer,
                                  ws.exception())
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            self.clients.discard(client)
            self.counters["dropped_by_gone"] += client.dropped
            sender.cancel()
            self._senders.discard(sender)
        return ws

    async def _bad(self, client: Client, cause: str, message: str) -> None:
        self.counters["bad_messages"] += 1
        self.rlog.log(("bad", cause), logging.WARNING, "console: client %s sent a bad message (%s): %s", client.peer,
                      cause, message)
        try:
            await client.ws.send_str(error_text(message))
        except (ConnectionError, RuntimeError):
            pass

    async def _command(self, client: Client, text: str) -> None:
        try:
            msg = json.loads(text)
        except ValueError:
            return await self._bad(client, "json", "not JSON")
        if not isinstance(msg, dict) or not isinstance(msg.get("cmd"), str):
            return await self._bad(client, "shape", 'expected {"cmd": "..."}')
        if msg["cmd"] == "health":
            client.offer(json.dumps({"type": "health", "health": self.health()}))
            return
        if msg["cmd"] == "rays":
            cam = msg.get("camera")
            if cam is not None and (isinstance(cam, bool) or cam not in self.view.cameras):
                return await self._bad(client, "rays", f"rays: camera {cam!r} is none of {sorted(self.view.cameras)}")
            client.rays = cam
            return
        if msg["cmd"] == "views":
            if not isinstance(msg.get("on"), bool):
                return await self._bad(client, "views", 'views: expected {"cmd": "views", "on": true or false}')
            client.views = msg["on"]
            return
        if msg["cmd"] in CALIBRATION_COMMANDS:
            return await self._calibration_command(client, msg)
        if msg["cmd"] == "record":
            try:
                reply = await self.recording.command(msg)
            except ValueError as e:
                return await self._bad(client, "record", str(e))
            text = json.dumps({"type": "record", **reply})
            for c in self.clients:  # every tab shows it at once; the sender's answer is never dropped
                if c is not client:
                    c.offer(text)
            try:
                await client.ws.send_str(text)
            except (ConnectionError, RuntimeError):
                pass
            return
        if msg["cmd"] == "write_pose":  # the page asked the operator first
            try:
                reply = write_monitored_pose(self.source, msg)
            except ValueError as e:
                return await self._bad(client, "write_pose", str(e))
            log.warning("console: camera %d's corrected pose written to %s (the old file: %s)", reply["camera"],
                        reply["file"], reply["backup"])
            try:
                await client.ws.send_str(json.dumps({"type": "pose_written", **reply}))
            except (ConnectionError, RuntimeError):
                pass
            return
        if msg["cmd"] in ("still", "mask"):
            try:
                self.stations.start(client, msg)
            except ValueError as e:
                return await self._bad(client, msg["cmd"], str(e))
            return
        if self.controls is None:
            return await self._bad(client, "cmd", f"unknown command {msg['cmd']!r} (replay controls need "
                                                  "`visionpos replay LOG --view`)")
        try:
            reply = await self.controls(msg)
        except ValueError as e:
            return await self._bad(client, "cmd", str(e))
        if reply is not None:  # an answer, not an update: never dropped
            try:
                await client.ws.send_str(json.dumps({"type": "replay", **reply}))
            except (ConnectionError, RuntimeError):
                pass

    async def _calibration_command(self, client: Client, msg: dict[str, Any]) -> None:
        """solve (record, replay --view, serve, demo); wave, ground and the applies (serve and demo: a running fusion
        server, console/live_calibration.py). An apply changes the running cameras: every tab gets the new scene."""
        cmd = msg["cmd"]
        if self.calibration is None:
            return await self._bad(client, cmd, f"{cmd}: no calibration assistant here (it runs in the console of "
                                                "`visionpos serve`, `demo`, `record` and `replay --view`)")
        if cmd not in getattr(self.calibration, "commands", ("solve",)):
            return await self._bad(client, cmd, f"{cmd}: only the console of a running fusion server (`visionpos "
                                                "serve`, `demo`) gathers a live wave, finds the ground frame or "
                                                "applies a calibration")
        try:
            reply = await self.calibration.command(msg)
        except ValueError as e:
            return await self._bad(client, cmd, str(e))
        if "applied" in reply:
            self._new_scene()
            for c in list(self.clients):
                try:
                    await c.ws.send_str(self._scene_text)
                except (ConnectionError, RuntimeError):
                    pass
        try:
            await client.ws.send_str(json.dumps({"type": "calib_reply", **reply}))
        except (ConnectionError, RuntimeError):
            pass

    def _new_scene(self) -> None:
        """The source's cameras moved (a calibration applied): the scene from its arena now, masks and the page's
        settings kept; its scene_id changes, so the page builds its views again."""
        fresh = scene(self.source.arena, getattr(self.source, "source_name", None),
                      getattr(self.source, "console_mode", "live"))
        masks = {c["id"]: c.get("mask") for c in self.view.scene["cameras"]}
        for cam in fresh["cameras"]:
            cam["mask"] = masks.get(cam["id"])
        self.view.scene = {**self.view.scene, **{k: fresh[k] for k in ("cameras", "scene_id", "calibration_rms_px")}}
        self.view.cameras = {c.id: c for c in self.source.arena.cameras}
        self.scene_changed()

    async def _sender(self, client: Client) -> None:
        try:
            while True:
                text = await client.queue.get()
                t0 = time.thread_time_ns()
                await client.ws.send_str(text)
                self.cpu_ns += time.thread_time_ns() - t0
                client.sent += 1
        except asyncio.CancelledError:
            raise
        except Exception as e:  # a closed tab mid-stream: its handler ends the client
            self.counters["send_errors"] += 1
            self.rlog.log(("send", type(e).__name__), logging.INFO, "console: a client went away mid-stream (%s)",
                          type(e).__name__)

    # ---------------------------------------------------------------- updates

    def publish_once(self, watch: bool = False) -> None:
        """One update tick: build, encode once (twice when some tabs want the camera views and some not), offer
        to every client (the update loop's body). watch: also run the view's residual and static-blob watches."""
        now = self.clock()
        rays = frozenset(c.rays for c in self.clients if c.views and c.rays is not None)
        viewers = sum(c.views for c in self.clients)
        # the camera views ride on camera_view_rate_hz of the updates, and only when a tab shows them; a watch
        # that falls due in between waits for the next of them (it reads the same views), or runs at once when no
        # tab shows them
        self._camera_credit = min(self._camera_credit + self._camera_share, 1.0)
        cameras = viewers > 0 and self._camera_credit >= 1.0 - 1e-9
        if cameras:
            self._camera_credit -= 1.0
        self._watch_due |= watch
        watch_now = self._watch_due and (cameras or viewers == 0)
        state = self.view.state(now, watch_now, rays, cameras=cameras)
        if watch_now:
            self._watch_due = False
        if self.extra is not None:
            state.update(self.extra())
        text = _encode(state)
        plain = text
        if cameras and viewers < len(self.clients):
            state.pop("cameras")
            plain = _encode(state)
        self.counters["updates"] += 1
        for c in self.clients:
            c.offer(text if c.views else plain)

    def publish_health(self) -> None:
        """The health (once a second) to every tab, and the calibration state again to a tab whose queue dropped
        something since it was last offered (only there: a third message would push out a state update)."""
        h = self.health()
        if not self.clients:
            return
        text = _encode({"type": "health", "health": h})
        for c in self.clients:
            c.offer(text)
        if self.calibration is not None:
            text = self._calib_text()
            for c in self.clients:
                if c.dropped != c.dropped_at_calib:
                    _offer_calib(c, text)

    def _calib_text(self) -> str:
        self._calib_version = self.calibration.version
        return json.dumps({"type": "calib", "calib": self.calibration.state()})

    async def _update_loop(self) -> None:
        period_s = 1.0 / self.settings.update_rate_hz
        next_health = next_watch = 0.0
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            next_t += period_s
            await asyncio.sleep(max(0.0, next_t - loop.time()))
            if loop.time() - next_t > 2 * period_s:  # the loop stalled: skip, never burst
                next_t = loop.time()
            t0 = time.thread_time_ns()
            try:
                now_s = loop.time()
                watch = now_s >= next_watch
                if watch:
                    next_watch = now_s + WATCH_PERIOD_S
                if self.clients:
                    self.publish_once(watch)
                    if self.calibration is not None and self.calibration.version != self._calib_version:
                        text = self._calib_text()
                        for c in self.clients:
                            _offer_calib(c, text)
                elif watch:
                    self.view.state(self.clock(), watch=True, cameras=False)
                if now_s >= next_health:  # also without clients: the rates of /api/health need samples
                    next_health = now_s + HEALTH_PERIOD_S
                    self.publish_health()
            except Exception:
                self.counters["update_errors"] += 1
                if self.counters["update_errors"] in (1, 100, 10_000):
                    log.exception("console: building an update failed (%d times)", self.counters["update_errors"])
            self.cpu_ns += time.thread_time_ns() - t0
