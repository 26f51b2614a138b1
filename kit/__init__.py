"""The kit: transport, logs, viewer, config, errors, geometry, metrics. Imports no stage."""
