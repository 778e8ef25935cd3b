"""``ctgpp evaluate --engine ray``: the episodes as Ray tasks, the results written by the parent.

Tasks are chunks of the episodes of one (set, scene, start), at most ``CHUNK`` episodes, one CPU and
one torch thread each. The scenes travel through Ray's object store (the cluster's nodes need ctgpp,
not the data); the policy factory travels pickled once, and each worker process unpickles it once
per run (its models load once per worker). A task whose worker dies runs again (``MAX_RETRIES``):
a chunk's results come back together or not at all, so a retry loses and duplicates nothing. The
first failed episode stops the run with its error, as with worker processes.
"""

from __future__ import annotations

import hashlib
import pickle
import traceback
from collections.abc import Generator, Mapping, Sequence
from typing import Any

import torch

from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import Episode, EpisodeResult, message_of, run_episode, user_error_kind
from ctgpp.eval.parallel import EpisodeFailed
from ctgpp.policies.factory import PolicyFactory
from ctgpp.ray_cluster import MAX_RETRIES, import_ray, ray_session
from ctgpp.scene.types import Scene

CHUNK = 4  # episodes per task

_FACTORY: tuple[str, PolicyFactory] | None = None  # this worker's factory, by the digest of its pickle


def _factory(blob: bytes) -> PolicyFactory:
    global _FACTORY
    digest = hashlib.sha1(blob).hexdigest()
    if _FACTORY is None or _FACTORY[0] != digest:
        _FACTORY = (digest, pickle.loads(blob))
    return _FACTORY[1]


def run_chunk(episodes: Sequence[Episode], blob: bytes, scene: Scene) -> list[EpisodeResult | EpisodeFailed]:
    """The chunk's episodes in a Ray worker, one torch thread; stops at the first that fails."""
    torch.set_num_threads(1)
    policies = _factory(blob)
    out: list[EpisodeResult | EpisodeFailed] = []
    for ep in episodes:
        try:
            out.append(run_episode(scene, ep, policies))
        except Exception as err:  # the parent raises it, labelled with its episode
            kind = user_error_kind(err)
            out.append(EpisodeFailed(ep, None if kind is None else kind.__name__, message_of(err),
                                     traceback.format_exc()))
            break
    return out


def ray_results(
    todo: Sequence[Episode], catalogs: Mapping[str, Catalog], policies: PolicyFactory, workers: int,
    address: str | None,
) -> Generator[EpisodeResult, None, None]:
    """Run ``todo`` on the Ray cluster at ``address`` (None: a Ray instance started here with
    ``workers`` CPUs) and yield each result as its chunk arrives."""
    ray = import_ray()
    with ray_session(ray, workers, address):
        remote = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(run_chunk)
        blob = ray.put(pickle.dumps(policies))
        scenes: dict[tuple[str, str], Any] = {}
        chunks: dict[tuple[str, str, float], list[Episode]] = {}
        for ep in todo:
            chunks.setdefault((ep.set, ep.scene, ep.start_s), []).append(ep)
            if (ep.set, ep.scene) not in scenes:
                scenes[(ep.set, ep.scene)] = ray.put(catalogs[ep.set].load(ep.scene))
        refs = [remote.remote(group[k:k + CHUNK], blob, scenes[(s, scene)])
                for (s, scene, _), group in chunks.items() for k in range(0, len(group), CHUNK)]
        while refs:
            finished, refs = ray.wait(refs, num_returns=1)
            for item in ray.get(finished[0]):
                if isinstance(item, EpisodeFailed):
                    for ref in refs:
                        ray.cancel(ref, force=True)
                    raise item.error()
                yield item
