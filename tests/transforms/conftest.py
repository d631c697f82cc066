import os
import sys

import torch

# toy_pixel_env.py must be importable by name in this process and in ParallelEnv workers (spawn
# copies sys.path into the children).
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)

torch.set_num_threads(1)
