"""Client side of the collider service: numpy + msgpack + httpx, no torch.

>>> from collider_client import Client
>>> with Client("http://127.0.0.1:8000") as client:      # remote: a running `collider serve`
...     result = client.query("bunny", points, fields=["distance", "contact"])
>>> client = Client(models="models/")                     # embedded: the engine in process

Points and results are world frame, metres. See :mod:`collider_client.response` for the
collision response a simulator applies after its step.
"""

from collider_contract import FIELDS, ModelInfo, QueryResult, SceneCollider

from ._base import USE_CLIENT_DEFAULT, RetryPolicy, UseClientDefault
from ._client import AsyncClient, Client
from ._exceptions import (
    BadRequestError,
    ColliderError,
    ConnectError,
    DeadlineExceededError,
    InvalidValueError,
    ModelNotFoundError,
    PayloadTooLargeError,
    ProtocolError,
    QueueFullError,
    RequestTimeoutError,
    ServerError,
    ServiceUnavailableError,
    TransportError,
    UnauthorizedError,
    UnsupportedMediaTypeError,
    error_for_status,
)
from .response import (
    ColliderPlacement,
    CollisionHook,
    collider_velocity,
    project_to_contacts,
    respond_velocities,
)

__all__ = [
    "FIELDS",
    "USE_CLIENT_DEFAULT",
    "AsyncClient",
    "BadRequestError",
    "Client",
    "ColliderError",
    "ColliderPlacement",
    "CollisionHook",
    "ConnectError",
    "DeadlineExceededError",
    "InvalidValueError",
    "ModelInfo",
    "ModelNotFoundError",
    "PayloadTooLargeError",
    "ProtocolError",
    "QueryResult",
    "QueueFullError",
    "RequestTimeoutError",
    "RetryPolicy",
    "SceneCollider",
    "ServerError",
    "ServiceUnavailableError",
    "TransportError",
    "UnauthorizedError",
    "UnsupportedMediaTypeError",
    "UseClientDefault",
    "collider_velocity",
    "error_for_status",
    "project_to_contacts",
    "respond_velocities",
]
