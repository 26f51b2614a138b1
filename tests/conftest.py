import sys
from pathlib import Path

# octolog before numpy: its __init__ pins OpenBLAS's kernels for this process as for every octolog
# process, so in-process results equal the CLI's bytes (docs/architecture.md, "Determinism").
import octolog  # noqa: F401

sys.path.insert(0, str(Path(__file__).resolve().parent))
