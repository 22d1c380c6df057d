"""Where a run's classes come from, end to end: ``gausem run`` with the DINOv2 segmenter and descriptor on a tiny
random-weight model written in the checkpoint format ``load_dinov2`` reads (a Hugging Face ``Dinov2Model`` directory,
as for the real ViT-S/14, with one layer), data without labels (the notice), and missing weight files."""
import json

import numpy as np
import pytest
import torch
from transformers import Dinov2Config, Dinov2Model

from gausem_core.cli import main
from gausem_core.config import SlamConfig
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset, write_tum_folder
from gausem_core.io.ply import read_gaussian_ply
from gausem_core.pipeline import Pipeline
from gausem_core.semantics import HeadInfo, save_head
from gausem_core.semantics.source import INERT_WITHOUT_LABELS

TINY_VITS14 = dict(hidden_size=384, num_hidden_layers=1, num_attention_heads=6, patch_size=14, image_size=56,
                   layerscale_value=1.0, mlp_ratio=1)  # ViT-S/14's token size and patch, one layer
FAST = ["--frames", "6", "--size", "80x60", "--quiet", "--set", "device=cpu", "--set", "mapping.init_iterations=60",
        "--set", "mapping.iterations=5", "--eval-every", "5"]
PLANT = SYNTHETIC_CLASSES.id_of("plant")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """A tiny random DINOv2 directory and a head that says 'plant' everywhere (zero weights, one-hot bias)."""
    root = tmp_path_factory.mktemp("semantics")
    torch.manual_seed(0)
    Dinov2Model(Dinov2Config(**TINY_VITS14)).save_pretrained(root / "dinov2")
    head = torch.nn.Linear(384, len(SYNTHETIC_CLASSES))
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(10.0 * torch.nn.functional.one_hot(torch.tensor(PLANT), len(SYNTHETIC_CLASSES)))
    save_head(root / "head.pt", head, HeadInfo(len(SYNTHETIC_CLASSES), 384, 14, 56, SYNTHETIC_CLASSES.names))
    return root / "dinov2", root / "head.pt"


def dinov2_settings(weights) -> list[str]:
    directory, head = weights
    return ["--set", "semantics.segmenter=dinov2", "--set", f"semantics.dinov2_weights={directory}",
            "--set", f"semantics.head_weights={head}"]


class Unlabelled(SyntheticDataset):
    """The synthetic walk as a sensor gives it: no labels, no class table."""

    class_table = None

    def _load(self, index):
        frame = super()._load(index)
        frame.labels = None
        return frame


@pytest.mark.slow
def test_gausem_run_segments_with_dinov2_and_describes_with_it(weights, tmp_path):
    assert (weights[0] / "config.json").is_file() and (weights[0] / "model.safetensors").is_file()
    out = tmp_path / "run"
    assert main(["run", "--dataset", "synthetic", *FAST, *dinov2_settings(weights), "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert metrics["semantics"] == {"source": "dinov2", "classes": len(SYNTHETIC_CLASSES), "evaluated": True,
                                    "inert": [], "descriptor": "dinov2"}
    # the map's classes are the segmenter's ('plant' everywhere), not the dataset's labels (many classes)
    labels = SyntheticDataset(resolution=(80, 60))[0].labels
    assert len(np.unique(labels)) >= 3 and (labels != PLANT).mean() > 0.9
    _, class_ids = read_gaussian_ply(out / "map.ply")
    assert len(class_ids) > 0 and set(np.unique(class_ids).tolist()) == {PLANT}
    # scored against the dataset's labels, which are mostly not 'plant'
    assert metrics["rendering"]["pixel_accuracy"] < 0.3


def test_pipeline_observations_carry_the_segmenters_labels(weights):
    directory, head = weights
    cfg = SlamConfig(device="cpu")
    cfg.semantics.segmenter, cfg.semantics.dinov2_weights, cfg.semantics.head_weights = "dinov2", str(directory), \
        str(head)
    pipeline = Pipeline(Unlabelled(resolution=(80, 60), max_frames=2), cfg, progress=False)
    obs = pipeline.observation(pipeline.dataset[0])
    assert pipeline.semantics.notice is None and pipeline.semantics.ground_truth(pipeline.dataset[0]) is None
    assert bool((obs.labels == PLANT).all())
    assert pipeline.semantics.class_table.names == SYNTHETIC_CLASSES.names  # the head's names, generic colours
    torch.testing.assert_close(obs.semantic[0, 0], pipeline.palette[PLANT])


def test_a_run_without_labels_says_once_what_is_inert(tmp_path, capsys):
    folder = write_tum_folder(Unlabelled(resolution=(80, 60), max_frames=3), tmp_path / "tum")
    out = tmp_path / "run"
    assert main(["run", "--dataset", f"tum:{folder}", *FAST, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count("the dataset has no labels") == 1
    assert "class-aware submap allocation" in printed and "semantics.segmenter: ade20k" in printed
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert metrics["semantics"]["source"] == "unlabelled" and metrics["semantics"]["inert"] == list(
        INERT_WITHOUT_LABELS)
    _, class_ids = read_gaussian_ply(out / "map.ply")
    assert class_ids is None


def test_labelled_runs_say_nothing():
    pipeline = Pipeline(SyntheticDataset(resolution=(80, 60), max_frames=1), SlamConfig(device="cpu"), progress=False)
    frame = pipeline.dataset[0]
    assert pipeline.semantics.notice is None and pipeline.semantics.kind == "labels"
    assert np.array_equal(pipeline.observation(frame).labels.numpy(), frame.labels)


@pytest.mark.parametrize("settings, error, message", [
    (["semantics.segmenter=dinov2"], FileNotFoundError, "semantics.dinov2_weights"),
    (["semantics.segmenter=dinov2", "semantics.dinov2_weights=WEIGHTS"], FileNotFoundError,
     "semantics.head_weights"),
    (["semantics.segmenter=dinov2", "semantics.dinov2_weights=ABSENT", "semantics.head_weights=HEAD"],
     FileNotFoundError, "semantics.dinov2_weights"),
    (["semantics.dinov2_weights=ABSENT"], FileNotFoundError, "semantics.dinov2_weights"),  # the descriptor's
    (["semantics.segmenter=mask2former"], ValueError, "semantics.segmenter must be one of"),
])
def test_missing_weights_and_unknown_segmenters_name_the_parameter(weights, tmp_path, settings, error, message):
    names = {"WEIGHTS": str(weights[0]), "HEAD": str(weights[1]), "ABSENT": str(tmp_path / "absent")}
    overrides = [arg for setting in settings for arg in ("--set", setting.split("=")[0] + "=" + names.get(
        setting.split("=")[1], setting.split("=")[1]))]
    with pytest.raises(error, match=message):
        main(["run", "--dataset", "synthetic", *FAST, *overrides, "--out", str(tmp_path / "run")])
