"""Semantic front end: segmenters (image -> class ids) and global / dense features of semantic colour images."""
from gausem_core.semantics.ade20k import Ade20kSegmenter
from gausem_core.semantics.backbone import Dinov2Backbone, load_dinov2
from gausem_core.semantics.descriptors import (ColourLayoutDescriptor, DescriptorExtractor, Dinov2Descriptor,
                                               make_descriptor)
from gausem_core.semantics.head import HeadInfo, load_head, save_head, train_linear_head
from gausem_core.semantics.segmenter import (Dinov2Segmenter, LabelsSegmenter, Segmenter, make_segmenter,
                                             segmenter_from_config)

__all__ = ["Ade20kSegmenter", "ColourLayoutDescriptor", "DescriptorExtractor", "Dinov2Backbone", "Dinov2Descriptor",
           "Dinov2Segmenter", "HeadInfo", "LabelsSegmenter", "Segmenter", "load_dinov2", "load_head", "make_descriptor",
           "make_segmenter", "save_head", "segmenter_from_config", "train_linear_head"]
