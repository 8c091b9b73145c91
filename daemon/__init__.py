"""The cdprd service: asyncio orchestration, CAN I/O, safety, zenoh, systemd and the CLI."""

import os

# One BLAS thread, set before numpy is first imported (an environment value wins).  The
# matrices here are 6x8; OpenBLAS's worker threads only cost: at the real-time core's
# priority they spin on its CPUs, at normal priority a cycle that hands them work waits
# while other work starves them (the demo's simulator stalled 5-20 ms with them).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
