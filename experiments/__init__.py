"""The paper's experiments (Figures 1-5) over the hedger_jax library; run ``python -m experiments``."""
