"""Solvers: batched damped Newton for implicit DEL steps, rollout loops."""
