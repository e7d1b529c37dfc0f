"""Peer (third-party) baselines used by the benchmarks."""
