"""OmegaConf resolvers used by the configs, registered on import of this module (the modules that
compose or read configs import it: cli, api, factory, runs, schema).

${scaled:N}  ->  max(1, round(N * epoch_scale)) with `epoch_scale` from the config root
               (1.0 = the paper's budget; conf/budget/reduced.yaml lowers it).
${len_or:x,d}  -> len(x), or d when x is null (e.g. the number of imported joints).
${max:a,b,...} -> the largest argument (e.g. a generated length covering train_steps).
${by_length:table,n} -> table[k] for the largest key k <= n of a {length: value} mapping (the smallest
               key when n is below every key), e.g. the paper's batch size by training length in Exp 2.
"""

from __future__ import annotations

from omegaconf import OmegaConf


def _scaled(n, *, _root_):
    scale = float(_root_.get("epoch_scale", 1.0))
    return max(1, int(round(float(n) * scale)))


def _by_length(table, n):
    items = sorted((int(k), v) for k, v in dict(table).items())
    if not items:
        raise ValueError("by_length: empty table")
    chosen = items[0][1]
    for k, v in items:
        if k <= int(n):
            chosen = v
    return chosen


def register() -> None:
    if not OmegaConf.has_resolver("scaled"):
        OmegaConf.register_new_resolver("scaled", _scaled)
    if not OmegaConf.has_resolver("len_or"):
        OmegaConf.register_new_resolver("len_or", lambda x, default: len(x) if x is not None else default)
    if not OmegaConf.has_resolver("max"):
        OmegaConf.register_new_resolver("max", lambda *xs: max(xs))
    if not OmegaConf.has_resolver("by_length"):
        OmegaConf.register_new_resolver("by_length", _by_length)


register()
