"""Detector model registry: known models, checksums, folder layout and download."""

from .registry import (
    ENV_MIRROR,
    ENV_MODELS,
    KNOWN_MODELS,
    ModelFile,
    ModelSpec,
    check_file,
    download,
    download_models,
    get_spec,
    list_models,
    model_path,
    resolve_models_dir,
    sha256_file,
    verify,
)

__all__ = [
    "ENV_MIRROR",
    "ENV_MODELS",
    "KNOWN_MODELS",
    "ModelFile",
    "ModelSpec",
    "check_file",
    "download",
    "download_models",
    "get_spec",
    "list_models",
    "model_path",
    "resolve_models_dir",
    "sha256_file",
    "verify",
]
