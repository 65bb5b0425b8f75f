"""The sharded evaluation's phases on a Dask cluster (``pip install "kitti-eval[cluster]"``).

``local:N`` starts a :class:`distributed.LocalCluster` of N worker processes for the run; ``tcp://HOST:PORT``
uses a running scheduler. Each task reads its own part's files (so the workers must reach the paths or
URLs given); the client only gathers the parts' summaries. Dask runs a task again elsewhere when its worker
is lost (up to ``retries`` times), which cannot change the numbers: a task is a pure function of its files.

Nothing here is imported unless a cluster is asked for, and dask is imported only then.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from ..errors import ConfigError

__all__ = ["cluster_mapper", "progress_mapper"]


def progress_mapper(show: bool) -> Callable[[Callable[[Any], Any], Sequence[Any]], list[Any]]:
    """The built-in map over parts, with a progress bar on stderr when ``show``."""

    def run(fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
        if not show:
            return [fn(x) for x in items]
        from tqdm import tqdm

        return [fn(x) for x in tqdm(items, desc=_phase_name(fn), unit="part", leave=False)]

    return run


def _phase_name(fn: Callable[[Any], Any]) -> str:
    name = type(fn).__name__
    return {"_Phase1": "phase 1", "_Phase2": "phase 2", "_Ids": "frame ids"}.get(name, name)


@contextlib.contextmanager
def cluster_mapper(
    address: str, *, progress: bool = False, retries: int = 2
) -> Iterator[Callable[[Callable[[Any], Any], Sequence[Any]], list[Any]]]:
    """A map over parts on the Dask cluster at ``address`` (``local:N`` or a scheduler address), for the
    duration of the ``with`` block."""
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as e:
        raise ConfigError(f"--cluster needs dask: pip install 'kitti-eval[cluster]' ({e})") from None
    if address.startswith("local:"):
        try:
            workers = int(address.split(":", 1)[1])
        except ValueError:
            workers = 0
        if workers < 1:
            raise ConfigError(f"--cluster {address!r}: expected local:N with N >= 1 worker processes")
        cluster: Any = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
        )
        client = Client(cluster)
    else:
        cluster = None
        try:
            client = Client(address, timeout="20s")
        except (OSError, TimeoutError, ValueError) as e:
            raise ConfigError(f"--cluster {address!r}: cannot reach the scheduler ({e})") from None

    def run(fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
        futures = client.map(fn, list(items), retries=retries, pure=False)
        if progress:
            from tqdm import tqdm

            with tqdm(total=len(futures), desc=_phase_name(fn), unit="part", leave=False) as bar:
                for _ in as_completed(futures):
                    bar.update()
        return list(client.gather(futures))

    try:
        yield run
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
