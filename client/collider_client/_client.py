"""``Client`` (sync) and ``AsyncClient`` (asyncio): one API, two backends.

- remote: ``Client("http://127.0.0.1:8000")`` talks msgpack over HTTP to ``collider serve`` with a
  pooled connection (httpx), a timeout and retries with backoff on 429/503 (``Retry-After``
  honoured), on refused connections, and, for queries (idempotent), on connections cut before
  the whole answer came;
- embedded: ``Client()`` or ``Client(models="models/")`` runs the engine in this process (needs the
  ``server`` extras).

Both give the same answers for the same calls. All points and results are world frame, metres.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import httpx
from typing_extensions import Self

from collider_contract import ModelInfo, ModelQuery, QueryError, QueryResult, SceneQuery, check_fields, wire

from ._base import (
    CUT,
    OTHER,
    REFUSED,
    USE_CLIENT_DEFAULT,
    Attempts,
    RetryPolicy,
    UseClientDefault,
    decode_models,
    decode_query,
    refusal,
)
from ._exceptions import ConnectError, RequestTimeoutError, TransportError

DEFAULT_TIMEOUT_S = 30.0


class _Settings:
    """What both clients hold: the backend choice and the per-call defaults."""

    def __init__(self, server: str | None, models, device, token, timeout_s, eps, fields,
                 retry: RetryPolicy | None):
        if server is not None and models is not None:
            raise ValueError("give either server= (remote) or models= (embedded), not both")
        if not (timeout_s is None or timeout_s > 0):
            raise ValueError(f"timeout_s must be > 0 or None, got {timeout_s}")
        self.server = server.rstrip("/") if server else None
        self.models = models
        self.device = device
        self.token = token
        self.timeout_s = timeout_s
        self.eps = eps
        self.fields = check_fields(fields)
        self.retry = retry or RetryPolicy()

    @property
    def remote(self) -> bool:
        return self.server is not None

    def headers(self) -> dict[str, str]:
        headers = {"Content-Type": wire.MSGPACK, "Accept": wire.MSGPACK}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        return headers

    def _defaults(self, fields, eps):
        return (self.fields if isinstance(fields, UseClientDefault) else fields,
                self.eps if isinstance(eps, UseClientDefault) else eps)

    def model_query(self, points, fields, pose, eps, only_colliding, time, pose_velocity,
                    clip=None, joint_transforms=None, joint_velocities=None) -> ModelQuery:
        """The call's query, validated by the contract (refused with the typed error the service
        would answer for it: the same by construction, whichever the backend)."""
        fields, eps = self._defaults(fields, eps)
        try:
            return ModelQuery.build(points, fields, pose, eps, only_colliding, time, pose_velocity,
                                    clip, joint_transforms, joint_velocities)
        except QueryError as exc:
            raise refusal(exc) from None

    def scene_query(self, colliders, points, fields, eps, only_colliding, time) -> SceneQuery:
        fields, eps = self._defaults(fields, eps)
        try:
            return SceneQuery.build(points, colliders, fields, eps, only_colliding, time)
        except QueryError as exc:
            raise refusal(exc) from None


def _with_deadline(body: dict, deadline_ms: float | None) -> dict:
    if deadline_ms is not None:
        body["deadline_ms"] = float(deadline_ms)
    return body


def _answer(attempts: Attempts, response: httpx.Response) -> tuple[dict | None, float]:
    """:meth:`Attempts.after_answer` for an httpx response."""
    return attempts.after_answer(response.status_code, response.content,
                                 response.headers.get("content-type", ""),
                                 response.headers.get("retry-after"))


def _failure(exc: httpx.TransportError) -> str:
    """What kind of transport failure ``exc`` is, for :meth:`Attempts.after_transport_error`."""
    if isinstance(exc, httpx.ConnectError):
        return REFUSED
    # The peer closed without (a whole) answer, or reset the connection while we read or wrote.
    if isinstance(exc, (httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError)):
        return CUT
    return OTHER


def _transport_error(exc: httpx.TransportError, url: str) -> TransportError:
    if isinstance(exc, httpx.TimeoutException):
        return RequestTimeoutError(f"{url}: timed out ({type(exc).__name__})")
    if isinstance(exc, httpx.ConnectError):
        return ConnectError(f"{url}: cannot connect ({exc})")
    return TransportError(f"{url}: {type(exc).__name__}: {exc}")


class Client:
    """Collision queries, synchronous. Use as a context manager or call :meth:`close`.

    server : URL of a running ``collider serve`` (remote backend); ``None`` = embedded
    models : model repository folder for the embedded backend (default ``models/``)
    device : embedded backend's torch device ("cpu", "cuda", None = CUDA if present)
    threads : embedded backend's torch CPU threads (process-wide; None = torch's default)
    token : bearer token sent as ``Authorization: Bearer <token>`` (remote)
    timeout_s : seconds per HTTP request (connect, read, write), None = no limit
    eps : default collision offset, world units (None = 1 mm)
    fields : default fields
    retry : :class:`RetryPolicy` for 429/503, refused connections and cut queries
    transport : an ``httpx.BaseTransport`` for special networks (remote only)
    """

    def __init__(self, server: str | None = None, *, models: str | Path | None = None,
                 device: str | None = None, threads: int | None = None,
                 token: str | None = None,
                 timeout_s: float | None = DEFAULT_TIMEOUT_S, eps: float | None = None,
                 fields: Iterable[str] = ("distance",), retry: RetryPolicy | None = None,
                 transport: httpx.BaseTransport | None = None):
        self._settings = _Settings(server, models, device, token, timeout_s, eps, fields, retry)
        self._http: httpx.Client | None = None
        self._embedded = None
        if self._settings.server is not None:  # remote
            self._http = httpx.Client(base_url=self._settings.server, timeout=timeout_s,
                                      headers=self._settings.headers(), transport=transport)
        else:
            from ._embedded import EmbeddedBackend

            self._embedded = EmbeddedBackend(models, device, threads)

    @property
    def remote(self) -> bool:
        """True when talking to a server, False when the engine runs in this process."""
        return self._settings.remote

    # -- the API --------------------------------------------------------------------------------

    def query(self, model: str, points, fields: Iterable[str] | UseClientDefault = USE_CLIENT_DEFAULT,
              pose=None, eps: float | None | UseClientDefault = USE_CLIENT_DEFAULT,
              deadline_ms: float | None = None, only_colliding: bool = False,
              time: float | None = None, pose_velocity=None, clip: str | None = None,
              joint_transforms=None, joint_velocities=None) -> QueryResult:
        """The ``fields`` of one collider at ``points``.

        points : (n, 3) float32/float64, world frame, metres
        pose : (4, 4) collider frame -> world frame, None = identity
        eps : collision offset, world units; ``None`` = 1 mm; not given = the client's default
        deadline_ms : how long the server may take (remote only; it answers 504 after that)
        only_colliding : compute ``normal``, ``contact`` and ``velocity`` only for points with
            ``distance < eps`` (cheaper); the others get ``normal`` and ``velocity`` [0, 0, 0]
            and ``contact`` equal to the point (``collides`` tells them apart)
        time : seconds, when an animated collider is asked (required for one; a static one
            ignores it)
        pose_velocity : (4, 4) the pose's time derivative (d(s R)/dt in 1/s, translation rate
            in m/s, bottom row 0), for the ``velocity`` field of a moving collider; None: still
        clip : a skinned collider's clip (None: its first), asked at ``time``
        joint_transforms : (J, 4, 4) a skinned collider's joints' world transforms, collider
            frame (instead of a clip); joint_velocities : (J, 4, 4) their time derivatives
            (1/s, m/s), for ``velocity``; None: a still skeleton
        """
        query = self._settings.model_query(points, fields, pose, eps, only_colliding, time,
                                           pose_velocity, clip, joint_transforms, joint_velocities)
        if self._embedded is not None:
            return self._embedded.query(model, query)
        body = self._post(f"/v1/models/{model}/query", _with_deadline(query.to_body(), deadline_ms),
                          idempotent=True)
        return decode_query(body, query.fields, scene=False)

    def scene_query(self, colliders: Sequence, points,
                    fields: Iterable[str] | UseClientDefault = USE_CLIENT_DEFAULT,
                    eps: float | None | UseClientDefault = USE_CLIENT_DEFAULT,
                    deadline_ms: float | None = None, only_colliding: bool = False,
                    time: float | None = None) -> QueryResult:
        """Per point, the ``fields`` of the nearest of several colliders (smallest signed
        distance) and ``collider``, its index in ``colliders``.

        colliders : model names, ``(model, pose)`` pairs, ``{"model", "pose", "time",
            "pose_velocity", "clip", "joint_transforms", "joint_velocities"}`` dicts or
            :class:`SceneCollider`; poses are 4x4 collider -> world
        time : seconds, the time of the colliders that give none of their own
        only_colliding : as in :meth:`query`
        """
        query = self._settings.scene_query(colliders, points, fields, eps, only_colliding, time)
        if self._embedded is not None:
            return self._embedded.scene_query(query)
        body = self._post("/v1/scene/query", _with_deadline(query.to_body(), deadline_ms),
                          idempotent=True)
        return decode_query(body, query.fields, scene=True)

    def list_models(self) -> list[ModelInfo]:
        """Every model the server (or the embedded repository) can answer for."""
        if self._embedded is not None:
            return self._embedded.list_models()
        return decode_models(self._send("GET", "/v1/models", None, idempotent=True))

    def ready(self) -> bool:
        """True when the server answers ``/readyz`` with 200 (always True when embedded)."""
        if self._embedded is not None:
            return True
        try:
            return self._remote().get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def close(self) -> None:
        """Release the connection pool (remote) or the loaded models (embedded)."""
        if self._http is not None:
            self._http.close()
        if self._embedded is not None:
            self._embedded.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- transport --------------------------------------------------------------------------------

    def _remote(self) -> httpx.Client:
        """The remote backend's connection pool (its calls come only when remote)."""
        assert self._http is not None
        return self._http

    def _post(self, path: str, body: dict, idempotent: bool) -> dict:
        return self._send("POST", path, wire.dumps(body, wire.MSGPACK), idempotent)

    def _send(self, method: str, path: str, content: bytes | None, idempotent: bool) -> dict:
        http = self._remote()
        attempts = Attempts(self._settings.retry, f"{self._settings.server}{path}", idempotent)
        while True:
            try:
                response = http.request(method, path, content=content)
            except httpx.TransportError as exc:
                delay = attempts.after_transport_error(_failure(exc),
                                                       _transport_error(exc, attempts.url))
            else:
                body, delay = _answer(attempts, response)
                if body is not None:
                    return body
            time.sleep(delay)


class AsyncClient:
    """:class:`Client` for asyncio: the same methods, awaited; ``aclose()`` and ``async with``.

    The embedded backend runs the engine in a worker thread so the event loop stays free.
    """

    def __init__(self, server: str | None = None, *, models: str | Path | None = None,
                 device: str | None = None, threads: int | None = None,
                 token: str | None = None,
                 timeout_s: float | None = DEFAULT_TIMEOUT_S, eps: float | None = None,
                 fields: Iterable[str] = ("distance",), retry: RetryPolicy | None = None,
                 transport: httpx.AsyncBaseTransport | None = None):
        self._settings = _Settings(server, models, device, token, timeout_s, eps, fields, retry)
        self._http: httpx.AsyncClient | None = None
        self._embedded = None
        if self._settings.server is not None:  # remote
            self._http = httpx.AsyncClient(base_url=self._settings.server, timeout=timeout_s,
                                           headers=self._settings.headers(), transport=transport)
        else:
            from ._embedded import EmbeddedBackend

            self._embedded = EmbeddedBackend(models, device, threads)

    @property
    def remote(self) -> bool:
        return self._settings.remote

    async def query(self, model: str, points,
                    fields: Iterable[str] | UseClientDefault = USE_CLIENT_DEFAULT, pose=None,
                    eps: float | None | UseClientDefault = USE_CLIENT_DEFAULT,
                    deadline_ms: float | None = None, only_colliding: bool = False,
                    time: float | None = None, pose_velocity=None, clip: str | None = None,
                    joint_transforms=None, joint_velocities=None) -> QueryResult:
        """See :meth:`Client.query`."""
        query = self._settings.model_query(points, fields, pose, eps, only_colliding, time,
                                           pose_velocity, clip, joint_transforms, joint_velocities)
        if self._embedded is not None:
            return await asyncio.to_thread(self._embedded.query, model, query)
        body = await self._post(f"/v1/models/{model}/query",
                                _with_deadline(query.to_body(), deadline_ms),
                                idempotent=True)
        return decode_query(body, query.fields, scene=False)

    async def scene_query(self, colliders: Sequence, points,
                          fields: Iterable[str] | UseClientDefault = USE_CLIENT_DEFAULT,
                          eps: float | None | UseClientDefault = USE_CLIENT_DEFAULT,
                          deadline_ms: float | None = None, only_colliding: bool = False,
                          time: float | None = None) -> QueryResult:
        """See :meth:`Client.scene_query`."""
        query = self._settings.scene_query(colliders, points, fields, eps, only_colliding, time)
        if self._embedded is not None:
            return await asyncio.to_thread(self._embedded.scene_query, query)
        body = await self._post("/v1/scene/query", _with_deadline(query.to_body(), deadline_ms),
                                idempotent=True)
        return decode_query(body, query.fields, scene=True)

    async def list_models(self) -> list[ModelInfo]:
        """See :meth:`Client.list_models`."""
        if self._embedded is not None:
            return await asyncio.to_thread(self._embedded.list_models)
        return decode_models(await self._send("GET", "/v1/models", None, idempotent=True))

    async def ready(self) -> bool:
        """See :meth:`Client.ready`."""
        if self._embedded is not None:
            return True
        try:
            return (await self._remote().get("/readyz")).status_code == 200
        except httpx.TransportError:
            return False

    async def aclose(self) -> None:
        if self._http is not None:
            await self._http.aclose()
        if self._embedded is not None:
            self._embedded.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()

    def _remote(self) -> httpx.AsyncClient:
        """The remote backend's connection pool (its calls come only when remote)."""
        assert self._http is not None
        return self._http

    async def _post(self, path: str, body: dict, idempotent: bool) -> dict:
        return await self._send("POST", path, wire.dumps(body, wire.MSGPACK), idempotent)

    async def _send(self, method: str, path: str, content: bytes | None,
                    idempotent: bool) -> dict:
        http = self._remote()
        attempts = Attempts(self._settings.retry, f"{self._settings.server}{path}", idempotent)
        while True:
            try:
                response = await http.request(method, path, content=content)
            except httpx.TransportError as exc:
                delay = attempts.after_transport_error(_failure(exc),
                                                       _transport_error(exc, attempts.url))
            else:
                body, delay = _answer(attempts, response)
                if body is not None:
                    return body
            await asyncio.sleep(delay)
