"""Ray plumbing for the ray executor's two jobs: joining or starting a cluster, what each task asks for, the
settings a driver must fix before its tasks run anywhere, and waiting on tasks so that a task's failure
reaches the user as the one-line error it raised.

Imported only when the ray executor is chosen (graftcache/executors/__init__.py names it by import string).
"""

from __future__ import annotations

import math
import os
import secrets
import signal
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import ray
import ray.exceptions

from graftcache.errors import ExecutorError, GraftcacheError, first_line
from graftcache.executors import Log
from graftcache.requests import ExecutorSettings
from graftcache.runtime import AUTO, resolve_compute_dtype, resolve_device
from graftcache.store.roots import cache_root, is_url, open_root

#: What a worker needs to behave like this process: the offline switches and where hub files, tiny policies
#: and caches live, plus the object store's endpoint and region, and for rollouts hf-libero's config folder and
#: MuJoCo's renderer. Handed to the workers as the job's runtime_env when this process starts or joins the
#: cluster. Credentials are not: each node brings its own (AWS_*, ...).
FORWARDED_ENV = ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_HOME", "HF_HUB_CACHE",
                 "HF_LEROBOT_HOME", "GRAFTCACHE_HOME", "TOKENIZERS_PARALLELISM", "AWS_ENDPOINT_URL", "AWS_REGION",
                 "AWS_DEFAULT_REGION", "LIBERO_CONFIG_PATH", "MUJOCO_GL", "PYOPENGL_PLATFORM")


def connect(settings: ExecutorSettings, log: Log) -> None:
    """Join the cluster at `settings.address`, or start a Ray instance on this machine; a process already
    connected (a notebook, the tests) keeps its connection and its runtime_env."""
    if ray.is_initialized():
        return
    env = {name: os.environ[name] for name in FORWARDED_ENV if name in os.environ}
    # a local instance started for one command needs no dashboard (a cluster's own `ray start` has one)
    local = {} if settings.address else {"include_dashboard": False}
    if not settings.address:
        use_local_token()
    log(f"ray: {'joining ' + settings.address if settings.address else 'starting a local Ray instance'}")
    try:
        with _own_stops():
            ray.init(address=settings.address, runtime_env={"env_vars": env}, **local)
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise ExecutorError(f"--address {settings.address}: cannot start or join Ray "
                            f"({' '.join(str(e).split())[:300]})") from None


#: Ray's own settings of its token authentication: where one is given, Ray's choice stands
RAY_AUTH_ENV = ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "RAY_AUTH_MODE")


def use_local_token() -> Path | None:
    """The token a Ray instance started here authenticates with, kept in the local cache folder
    (graftcache.store.cache_root: ray/auth_token, made once, readable by this user only) instead of the
    ~/.ray/auth_token Ray writes otherwise: graftcache writes nothing outside its folders. None where Ray's own
    settings (RAY_AUTH_ENV) say otherwise."""
    if any(name in os.environ for name in RAY_AUTH_ENV):
        return None
    path = cache_root() / "ray" / "auth_token"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{os.getpid()}")
        partial.write_text(secrets.token_hex(32))
        partial.chmod(0o600)
        os.replace(partial, path)  # two commands starting at once: either token, whole
    os.environ["RAY_AUTH_TOKEN_PATH"] = str(path)
    return path


@contextmanager
def _own_stops() -> Iterator[None]:
    """This process's SIGINT and SIGTERM handlers (the command's one-line stop, graftcache.cli.signals) kept over
    ray.init, which replaces them: its driver's core worker installs a C++ handler that answers SIGTERM with a stack
    dump and an abort (exit 134). Set again from Python, the command's handlers are the ones the kernel calls."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def task_options(settings: ExecutorSettings, device: str) -> dict[str, Any]:
    """Ray's options for one task on `device`: its CPUs and GPUs, retried when its worker or node dies (system
    failures), never when it raised: a GraftcacheError is bad input and would fail again."""
    if device.startswith("cuda:"):
        raise ExecutorError(f"--device {device} with the ray executor: Ray gives each task its GPUs "
                            f"(CUDA_VISIBLE_DEVICES); pass --device cuda")
    gpus = settings.gpus_per_task if settings.gpus_per_task is not None else float(device == "cuda")
    if device == "cuda" and not gpus:
        raise ExecutorError("--device cuda with --gpus-per-task 0: a task would get no GPU")
    return {"num_cpus": settings.cpus_per_task, "num_gpus": gpus, "max_retries": settings.max_retries,
            "retry_exceptions": False}


def slots(options: Mapping[str, Any]) -> int:
    """How many tasks with these options the cluster runs at once (its GPUs, else its CPUs, over one task's
    share); a cluster that cannot place one such task is an error here rather than a task pending forever."""
    kind, need = ("GPU", options["num_gpus"]) if options["num_gpus"] else ("CPU", options["num_cpus"])
    have = ray.cluster_resources().get(kind, 0.0)
    n = math.floor(have / need + 1e-9)
    if n < 1:
        raise ExecutorError(f"the Ray cluster has {have:g} {kind}(s), a task asks for {need:g}")
    return n


def local_path(value: str | None) -> str | None:
    """An existing local path made absolute (a worker's working folder is not this process's), anything else
    (a hub id, a URL, None) as given."""
    return str(Path(value).resolve()) if value and not is_url(value) and Path(value).exists() else value


def shared_root(cache: str | None) -> str:
    """The cache root every task uses, named so that any process resolves it to the same place: a URL as
    is, a folder absolute; the default ($GRAFTCACHE_HOME, ~/.cache/graftcache) is decided here, once."""
    url = open_root(cache).url
    return url if is_url(url) else str(Path(url).resolve())


@ray.remote
def _resolve_compute_dtype(name: str, device: str) -> str:
    return resolve_compute_dtype(name, resolve_device(device))


def worker_compute_dtype(name: str, device: str, options: Mapping[str, Any]) -> str:
    """`auto` resolved where the tasks run, by one task with their resources: cache keys and run_ids hold
    the resolved dtype, which a CPU-only head node would decide differently than the GPUs that compute."""
    if name != AUTO:
        return name
    ((_, resolved),) = finished({_resolve_compute_dtype.options(**options).remote(name, device): "compute dtype"})
    return resolved


def result(ref: ray.ObjectRef, tag: str) -> Any:
    """What a finished task returned. A task that raised a GraftcacheError (or an OSError such as a full disk)
    raises it here as itself, one line, not Ray's remote traceback; a task lost more often than it may be retried
    is an ExecutorError naming `tag`."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as e:
        if isinstance(e.cause, (GraftcacheError, OSError)):
            raise e.cause from None
        raise
    except ray.exceptions.RayError as e:
        raise ExecutorError(f"{tag}: {type(e).__name__}: {first_line(e)}") from None


def finished[R](tasks: Mapping[ray.ObjectRef, R]) -> Iterator[tuple[R, Any]]:
    """(tag, result) of each task as it finishes (`result`: a task's error raised as the command's). Either way,
    and when the caller stops early, the rest are cancelled."""
    pending = list(tasks)
    try:
        while pending:
            (ready,), pending = ray.wait(pending, num_returns=1)
            yield tasks[ready], result(ready, str(tasks[ready]))
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
