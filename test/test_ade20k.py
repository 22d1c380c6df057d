"""The ade20k segmenter: its class mapping, its errors, and the shared model on real and synthetic frames."""
import cv2
import numpy as np
import pytest

from gausem_core.config import SemanticsConfig, SlamConfig
from gausem_core.data import NYU40_CLASSES, SyntheticDataset, TumDataset
from gausem_core.pipeline import Pipeline
from gausem_core.semantics import Ade20kSegmenter, segmenter_from_config
from gausem_core.semantics.ade20k import (ADE20K_CLASSES, INPUT_SIDE, MAPPING_FILE, MODEL_FILE, ade20k_to_nyu40,
                                          crop_back, letterbox)


def test_every_ade20k_class_maps_to_an_nyu40_class():
    lut = ade20k_to_nyu40()
    assert lut.shape == (ADE20K_CLASSES,) and lut.min() >= 0 and lut.max() < len(NYU40_CLASSES)
    names = {line.split()[1]: NYU40_CLASSES.names[lut[int(line.split()[0])]]
             for line in MAPPING_FILE.read_text().splitlines() if line and not line.startswith("#")}
    assert names["wall"] == "wall" and names["floor"] == "floor" and names["armchair"] == "chair"
    assert names["painting"] == "picture" and names["sky"] == "unlabelled" and names["monitor"] == "television"
    assert len(set(lut.tolist())) > 30  # most NYU40 classes are reachable


def test_a_mapping_file_that_misses_a_class_is_an_error(tmp_path):
    lines = [line for line in MAPPING_FILE.read_text().splitlines() if not line.startswith("17 ")]
    (tmp_path / "map.txt").write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"ADE20K ids \[17\]"):
        ade20k_to_nyu40(tmp_path / "map.txt")


@pytest.mark.parametrize("shape", [(120, 160), (480, 640), (640, 480), (37, 513), (700, 1000)])
def test_letterbox_and_crop_back_return_each_pixel_to_its_place(shape):
    rng = np.random.default_rng(0)
    blocks = rng.integers(0, 2, (6, 8)).astype(np.uint8)  # bright and dark blocks, a few pixels each at any scale
    rgb = np.repeat(cv2.resize(blocks * 255, shape[::-1], interpolation=cv2.INTER_NEAREST)[..., None], 3, axis=2)
    batch, fit = letterbox(rgb)
    assert batch.shape == (1, INPUT_SIDE, INPUT_SIDE, 3) and max(fit) == INPUT_SIDE
    assert batch.min() >= -1 and batch.max() <= 1 and not batch[0, fit[0]:].any() and not batch[0, :, fit[1]:].any()
    model = (batch[0, ..., 0] > 0).astype(np.int64)  # a "model" that calls bright pixels class 1
    recovered = crop_back(model, fit, shape)
    assert recovered.shape == shape
    assert (recovered == (rgb[..., 0] > 127)).mean() > 0.97  # all but pixels on block edges


@pytest.mark.parametrize("given", [True, False])
def test_a_missing_model_names_the_parameter(tmp_path, monkeypatch, given):
    monkeypatch.setenv("GAUSEM_SHARED_MODELS", str(tmp_path))
    cfg = SemanticsConfig(segmenter="ade20k", ade20k_model=str(tmp_path / "nope.tflite") if given else "")
    with pytest.raises(FileNotFoundError, match="semantics.ade20k_model"):
        segmenter_from_config(cfg)


@pytest.fixture(scope="module")
def segmenter(ade20k_model):
    return Ade20kSegmenter(ade20k_model, threads=2)


def test_the_model_labels_a_real_office_frame_with_several_classes_that_a_mirror_image_keeps(segmenter,
                                                                                               shared_data):
    frame = TumDataset(shared_data / "tum_fr1_rpy")[0]
    labels = segmenter.segment(frame.rgb)
    assert labels.shape == frame.rgb.shape[:2] and labels.dtype == np.int64
    assert labels.min() >= 0 and labels.max() < len(NYU40_CLASSES)
    counts = np.bincount(labels.ravel(), minlength=len(NYU40_CLASSES)) / labels.size
    assert (counts > 0.02).sum() >= 3  # an office: several classes, each on a visible share of the image
    assert counts[NYU40_CLASSES.id_of("wall")] > 0.3  # the first frame looks at a wall above the desk
    # the mirrored image gets mostly the mirrored labels (the model itself is not symmetric: about 3/4 agree)
    mirrored = segmenter.segment(np.ascontiguousarray(frame.rgb[:, ::-1]))[:, ::-1]
    assert (mirrored == labels).mean() > 0.6


def test_pipeline_segments_every_frame_into_the_nyu40_table(ade20k_model):
    cfg = SlamConfig()
    cfg.semantics = SemanticsConfig(segmenter="ade20k", ade20k_model=str(ade20k_model))
    data = SyntheticDataset("default", resolution=(80, 60), max_frames=2)
    pipeline = Pipeline(data, cfg, progress=False)
    assert pipeline.semantics.kind == "ade20k" and pipeline.semantics.class_table is NYU40_CLASSES
    assert pipeline.semantics.ground_truth(data[0]) is None  # the synthetic classes are not NYU40's
    obs = pipeline.observation(data[0])
    assert obs.labels.shape == (60, 80) and int(obs.labels.max()) < len(NYU40_CLASSES)
    assert pipeline.semantics.summary()["source"] == "ade20k"


def test_gausem_info_says_where_the_model_is_or_which_parameter_to_set(tmp_path, monkeypatch):
    from gausem_core.tools.info import ade20k_model_status
    monkeypatch.setenv("GAUSEM_SHARED_MODELS", str(tmp_path))
    assert ade20k_model_status().startswith("absent") and "semantics.ade20k_model" in ade20k_model_status()
    (tmp_path / MODEL_FILE).parent.mkdir()
    (tmp_path / MODEL_FILE).write_bytes(b"")
    assert ade20k_model_status() == str(tmp_path / MODEL_FILE)
