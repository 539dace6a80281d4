"""Inference over topologies (thesis Ch. 3): the Rao-Blackwellized particle filter, MCMC with MC³ and
its convergence diagnostics, and the filter's persistence. Built on :mod:`ptm_ros.model`."""
