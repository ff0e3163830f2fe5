"""Ground-truth data: rigid-body simulators, scene generators, the HDF5 dataset format."""

from ..errors import CheckpointError, ConfigError, DatasetError, LiedflError, SimulationError
from .hdf5 import FORMAT_VERSION, Dataset, load_dataset, save_dataset
from .physics import RigidBodySE3, RigidBodySO3, SolverOptions, simulate_se3, simulate_so3
from .scenes import SCENES, config_hash, dataset_path, generate, get_dataset

__all__ = [
    "CheckpointError",
    "ConfigError",
    "DatasetError",
    "LiedflError",
    "SimulationError",
    "FORMAT_VERSION",
    "Dataset",
    "load_dataset",
    "save_dataset",
    "RigidBodySE3",
    "RigidBodySO3",
    "SolverOptions",
    "simulate_se3",
    "simulate_so3",
    "SCENES",
    "config_hash",
    "dataset_path",
    "generate",
    "get_dataset",
]
