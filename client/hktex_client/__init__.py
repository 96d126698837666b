"""Typed Python client of the HKTex service (sync and async, over httpx and pydantic).

Light on purpose: httpx, pydantic and numpy only, so asset tools can call a shared HKTex
server without installing torch, scipy or mitsuba.
"""

from hktex_client.client import AsyncClient, Client
from hktex_client.errors import (
    BadRequest,
    Conflict,
    HKTexAPIError,
    HKTexClientError,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    ServerError,
    Unauthorized,
    UnsupportedMediaType,
    ValidationFailed,
    WaitTimeout,
)
from hktex_client.models import (
    FINAL_STATES,
    BakeInfo,
    Health,
    Info,
    JobProgress,
    JobRecord,
    JobResult,
    KernelSetRecord,
    MeshRecord,
    SpectraRecord,
    ViewsRecord,
)
from hktex_client.npy import NPY_MEDIA_TYPE, from_npy_bytes, to_npy_bytes
from hktex_client.sse import ServerSentEvent

__version__ = "0.1.0"

__all__ = [
    "FINAL_STATES",
    "NPY_MEDIA_TYPE",
    "AsyncClient",
    "BadRequest",
    "BakeInfo",
    "Client",
    "Conflict",
    "HKTexAPIError",
    "HKTexClientError",
    "Health",
    "Info",
    "JobFailed",
    "JobProgress",
    "JobRecord",
    "JobResult",
    "KernelSetRecord",
    "MeshRecord",
    "NotFound",
    "PayloadTooLarge",
    "ServerError",
    "ServerSentEvent",
    "SpectraRecord",
    "Unauthorized",
    "UnsupportedMediaType",
    "ValidationFailed",
    "ViewsRecord",
    "WaitTimeout",
    "__version__",
    "from_npy_bytes",
    "to_npy_bytes",
]
