"""Logged transitions: the validated container, its file formats, the collection recipe."""

from torch_gpmpc.data.collect import MAX_COLLECT_ROWS, collect_transitions, sample_disc
from torch_gpmpc.data.formats import SUFFIXES, check_suffix, csv_header
from torch_gpmpc.data.transitions import Transitions

__all__ = ["MAX_COLLECT_ROWS", "SUFFIXES", "Transitions", "check_suffix", "collect_transitions", "csv_header",
           "sample_disc"]
