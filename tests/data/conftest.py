import os
import sys

import torch

# share the toy pixel env of the transform tests (importable by name, also in spawned workers)
_TOY = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "transforms")
if _TOY not in sys.path:
    sys.path.insert(0, _TOY)

torch.set_num_threads(1)
