"""The shell: the CLI and the orchestration of the stages; the only floor that imports several stages."""
