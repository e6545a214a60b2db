"""Demos, one module per tracker: simulate its input, track it, print the paper's tables
(``gputrack demo <name>`` runs :func:`gputrack.demos.<name>.run`)."""
