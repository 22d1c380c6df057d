"""Datasets: frames (rgb, depth in metres, labels, camera, timestamp, ground-truth pose) from folders or the
procedural scene. Open any of them with :func:`open_dataset`."""
from gausem_core.data.classes import NYU40_CLASSES, SCANNET20_CLASSES, SYNTHETIC_CLASSES, ClassTable
from gausem_core.data.export import write_tum_folder
from gausem_core.data.frame import Dataset, Frame, resize_frame
from gausem_core.data.replica import ReplicaDataset
from gausem_core.data.scannet import ScanNetDataset
from gausem_core.data.spec import open_dataset
from gausem_core.data.synthetic import SyntheticDataset
from gausem_core.data.tum import TumDataset

__all__ = ["ClassTable", "Dataset", "Frame", "NYU40_CLASSES", "ReplicaDataset", "SCANNET20_CLASSES",
           "SYNTHETIC_CLASSES", "ScanNetDataset", "SyntheticDataset", "TumDataset", "open_dataset", "resize_frame",
           "write_tum_folder"]
