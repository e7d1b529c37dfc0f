"""Labelled-run simulators with known truth (wheeled robot with slip and GNSS outages)."""

from msf_torch.sim.wheeled import (
    SLIP_TYPES,
    GroundPath,
    ImuNoiseSpec,
    PathState,
    SimConfig,
    SimTruth,
    SimulatedRun,
    SlipEpisode,
    default_slip_config,
    gnss_denied_slip_config,
    sample_slip_config,
    simulate_run,
)

__all__ = [
    "SLIP_TYPES",
    "GroundPath",
    "ImuNoiseSpec",
    "PathState",
    "SimConfig",
    "SimTruth",
    "SimulatedRun",
    "SlipEpisode",
    "default_slip_config",
    "gnss_denied_slip_config",
    "sample_slip_config",
    "simulate_run",
]
