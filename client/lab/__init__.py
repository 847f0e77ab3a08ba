"""The lab (extra ``[lab]``): synthetic route world, experiments, benchmarks and plots.

Nothing in ``service/`` or the light client imports it.
"""
