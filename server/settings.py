"""Service settings, from the environment (``HKTEX_*``) and the command line.

One object carries every limit so a deployment can tighten them without code; the defaults
suit one shared workstation (SQLite under the data dir, loopback only, one worker slot).
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

LOCAL_OWNER = "local"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="HKTEX_", extra="ignore")

    data_dir: Path = Field(Path("hktex-data"), description="blobs, spectra, kernel sets, SQLite")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; SQLite in data_dir if unset"
    )
    host: str = "127.0.0.1"
    port: int = 8000
    tokens: str = Field("", description='"token1:owner1,token2:owner2"')

    # supervisor
    workers: int = Field(1, ge=0, description="job slots of an embedded/standalone supervisor")
    devices: str = Field("", description='CUDA device ids for the slots ("0,1"); "" = auto')
    lease_seconds: float = 30.0
    heartbeat_seconds: float = 5.0
    poll_seconds: float = 0.5
    cancel_grace_seconds: float = 10.0
    kill_grace_seconds: float = 5.0
    max_attempts: int = Field(3, ge=1)
    enable_test_tasks: bool = Field(False, description="allow the internal 'sleep' job (tests)")
    job_threads: int | None = Field(
        None,
        ge=1,
        description="CPU threads per job process (torch/OpenMP/BLAS); default cores // workers",
    )
    warm_jobs: bool = Field(
        True,
        description="fork job processes from a forkserver with the engine imported "
        "(False: a fresh interpreter per job, paying the imports)",
    )
    fit_eval_points: int | None = Field(
        None, ge=100, description="surface points for a fit's final metrics (engine default)"
    )

    # limits
    max_upload_bytes: int = 512 * 1024 * 1024
    max_archive_bytes: int = 2 * 1024 * 1024 * 1024
    max_archive_members: int = 20_000
    max_vertices: int = 60_000
    max_batch_points: int = 2_000_000
    max_json_batch_points: int = Field(
        100_000, description="JSON bodies cost ~100x NPY to parse: big batches must use NPY"
    )
    max_jobs_per_owner: int = Field(50, description="queued + running jobs an owner may hold")
    max_running_per_owner: int = Field(2, description="fair share: running jobs per owner")
    validate_timeout_seconds: float = 120.0
    query_cache_size: int = Field(4, ge=1, description="warm kernel sets per compute worker")
    query_chunk_points: int = Field(65_536, ge=1)

    # request-time compute (albedo queries, renders): server/api/compute.py
    compute_workers: int | None = Field(
        None, ge=1, le=256, description="worker processes for queries and renders; default cores"
    )
    compute_threads: int = Field(1, ge=1, le=256, description="CPU threads per compute worker")
    compute_nice: int = Field(
        5, ge=0, le=19, description="niceness of compute workers: the API's own loop comes first"
    )
    compute_timeout_seconds: float = Field(
        60.0, gt=0, description="run time one query or render may take before it is killed"
    )
    compute_memory_bytes: int = Field(
        4 * 1024**3, ge=64 * 1024**2, description="address space one request may add (RLIMIT_AS)"
    )
    compute_recycle_bytes: int = Field(
        1536 * 1024**2, ge=64 * 1024**2, description="a worker this big after a request retires"
    )
    max_queued_per_owner: int = Field(64, ge=1, description="waiting compute requests (then 429)")
    max_render_samples: int = Field(
        2**26, ge=1, description="width x height x spp of one render (then 422)"
    )
    shutdown_grace_seconds: float = Field(
        3.0, ge=0, description="on SIGTERM, how long open requests and streams may finish"
    )

    def compute_workers_resolved(self) -> int:
        """Compute workers: the setting, else one per core this process may run on."""
        if self.compute_workers:
            return self.compute_workers
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except (AttributeError, OSError):  # not Linux
            return max(1, os.cpu_count() or 1)

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'hktex.db').resolve()}"

    def token_owners(self) -> dict[str, str]:
        """Parse ``tokens`` into {token: owner}; malformed entries are a startup error."""
        owners: dict[str, str] = {}
        for entry in filter(None, (e.strip() for e in self.tokens.split(","))):
            token, sep, owner = entry.partition(":")
            if not sep or not token.strip() or not owner.strip():
                raise ValueError(f"HKTEX_TOKENS entry {entry!r} is not 'token:owner'")
            owners[token.strip()] = owner.strip()
        return owners

    def threads_per_job(self) -> int:
        """CPU threads one job process may use: ``job_threads``, else the cores this process
        may run on shared evenly by the slots (N jobs each using every core oversubscribe the
        machine: measured 10-45x slowdowns on a loaded 2-core host)."""
        if self.job_threads:
            return self.job_threads
        try:
            cores = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):  # not Linux
            cores = os.cpu_count() or 1
        return max(1, cores // max(1, self.workers))

    def device_list(self) -> list[str]:
        return [d.strip() for d in self.devices.split(",") if d.strip()]

    def check_bind(self) -> None:
        """Refuse to listen beyond loopback without tokens (anyone could read everyone's data)."""
        if not self.token_owners() and not is_loopback(self.host):
            raise ValueError(
                f"refusing to bind {self.host} without tokens: set HKTEX_TOKENS or bind 127.0.0.1"
            )


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
