"""Datasets of optimal trajectory segments: generation (Alg. 2), cleaning (Alg. 3), storage."""

from rrtcolearn.data.dataset import Dataset

__all__ = ["Dataset"]
