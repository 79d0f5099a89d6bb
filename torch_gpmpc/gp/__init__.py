"""Residual GPs: the model, its prediction cache and standardization, fitting, files, evaluation."""

from torch_gpmpc.gp.evaluation import holdout_metrics
from torch_gpmpc.gp.fit import (
    MAX_TRAINING_POINTS, check_gp_inputs, check_training_size, fit_agent_gp, fit_agent_gps, fit_from_transitions,
    fit_per_agent, fit_residual_gp, gp_input_label, load_model_gp, residual_label,
)
from torch_gpmpc.gp.model import GP_INPUTS, ResidualGP

__all__ = ["GP_INPUTS", "MAX_TRAINING_POINTS", "ResidualGP", "check_gp_inputs", "check_training_size",
           "fit_agent_gp", "fit_agent_gps", "fit_from_transitions", "fit_per_agent", "fit_residual_gp",
           "gp_input_label", "holdout_metrics", "load_model_gp", "residual_label"]
