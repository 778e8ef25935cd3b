"""What a denoiser call reads that stays fixed across the denoising steps of one batch: the encoded
context (:meth:`Denoiser.encode_context <ctgpp.model.denoiser.Denoiser.encode_context>`) and its
expansion to several samples per scene.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from torch import Tensor

from ctgpp.model.attention import FoldedKeys, sample_rows
from ctgpp.model.neighbours import Neighbours


def repeat_samples(value: Tensor, n: int) -> Tensor:
    """(S, ...) -> (S*n, ...): each scene's row repeated for its ``n`` samples, scene-major; a view
    when S is 1."""
    if value.shape[0] == 1:
        return value.expand(n, *value.shape[1:])
    return value.repeat_interleave(n, dim=0)


@dataclass(frozen=True, eq=False)
class DenoiserContext:
    """What stays fixed across the denoising steps of one batch (computed once per sample call).

    agent_mask (S, A); current (S, A, 4) current states in the input frame; hist_tokens (S, A, H, d);
    token_valid (S, A, H+F); edges (S or 1, H+F, A, K, E) embedded e_ij; spatial_mask (S or 1, H+F, A, K)
    (both None when the spatial attention runs over ``neighbours``);
    map_keys: per block, each agent's L lane tokens folded into that block's map attention
    (:class:`FoldedKeys` with leading dimensions (S, A)). agent_tokens (S, A, 1, d): the agent
    embedding added to every future token (None for models without context). context_keys: per
    block, the context agents' keys and values (S or 1, T, C, 2, h, dh) of its spatial attention
    (None without context). groups: the spatial attention's neighbourhood groups
    (:func:`~ctgpp.model.attention.neighbourhood_groups`; None: one dense attention).
    sample_context_keys: ``context_keys`` with a row per sample (S*n, T, C, 2, h, dh), made once by
    :meth:`expand` for the dense spatial attention, which would otherwise repeat them at every call
    (None: not made). neighbours: each agent's keys within the social radius, for the gathered
    spatial attention (:mod:`~ctgpp.model.neighbours`; None: dense or by groups), with context_tokens
    per block the context agents' tokens through its spatial attention's norm (S or 1, T, C, d).
    """

    agent_mask: Tensor
    current: Tensor
    hist_tokens: Tensor
    token_valid: Tensor
    edges: Tensor | None
    spatial_mask: Tensor | None
    map_keys: tuple[FoldedKeys, ...]
    agent_tokens: Tensor | None = None
    context_keys: tuple[Tensor, ...] | None = None
    groups: list[tuple[Tensor, Tensor]] | None = None
    sample_context_keys: tuple[Tensor, ...] | None = None
    neighbours: Neighbours | None = None
    context_tokens: tuple[Tensor, ...] | None = None

    def expand(self, n: int) -> DenoiserContext:
        """The context of S scenes for ``n`` samples each: (S, ...) -> (S*n, ...), scene-major rows
        (the n samples of scene 0, then of scene 1, ...); views when S is 1.

        Encoding once and expanding saves n − 1 encodings of the same scene (history, edges, lanes).
        ``edges``, ``spatial_mask`` and ``context_keys``, the largest, keep their S rows: the spatial
        attention shares each scene's among its samples. What every denoising step would otherwise
        copy from views is copied here once: the folded lane keys (the map attention's batched
        matmuls take their (S*n*A) rows contiguous) and, for the dense spatial attention, the context
        keys per sample (``sample_context_keys``).
        """
        kept = ("edges", "spatial_mask", "map_keys", "agent_tokens", "context_keys", "groups",
                "sample_context_keys", "neighbours", "context_tokens")
        expanded = {
            f.name: repeat_samples(getattr(self, f.name), n) for f in fields(self) if f.name not in kept
        }
        map_keys = tuple(keys.map(lambda v: repeat_samples(v, n).contiguous()) for keys in self.map_keys)
        agent = None if self.agent_tokens is None else repeat_samples(self.agent_tokens, n)
        per_sample = None
        if self.context_keys is not None and self.groups is None and self.neighbours is None:
            rows = self.agent_mask.shape[0] * n  # the rows after this one
            per_sample = tuple(sample_rows(keys, rows // keys.shape[0]) for keys in self.context_keys)
        return DenoiserContext(
            **expanded,
            edges=self.edges,
            spatial_mask=self.spatial_mask,
            map_keys=map_keys,
            agent_tokens=agent,
            context_keys=self.context_keys,
            groups=self.groups,
            sample_context_keys=per_sample,
            neighbours=self.neighbours,
            context_tokens=self.context_tokens,
        )
