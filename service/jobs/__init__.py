"""Job kinds (kinds.py: train, render, export, each a registry entry) and the one attempt runner
(attempt.py) that takes any of them through its lease, fence, retry and cancel. Nothing here imports
PyTorch at module level: a kind's work (train.py, render.py, export.py) is loaded by the process
that runs an attempt."""
