"""Bladed-disk modal model: parametric FE builder, mistuning, and the ``.npz`` model file."""

from .bladed_disk import BladedDiskDesign
from .modal_model import ModalModel, build_model, load_model, localisation, save_model

__all__ = ["BladedDiskDesign", "ModalModel", "build_model", "load_model", "save_model", "localisation"]
