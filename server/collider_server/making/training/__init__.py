"""Train a ``neural`` collider from a mesh (the paper's recipe, with a few additions).

Data: exact signed distances (float64, libigl closest point + fast winding number sign) at
``samples`` points: ``near_fraction`` near the surface (surface samples plus uniform noise within
``margin``; a share ``tight_fraction`` of those within ``tight_margin``, the band where collisions
are decided) and the rest uniform in the padded domain box. The set is computed once and cached
(cheaper than fresh samples each epoch and it converged as well in our runs).

Loss: L1 on the distance (the paper's choice), plus, when ``normal_weight > 0``, ``1 - cos`` between
the network's gradient and the exact gradient (direction to the closest point) on the near
samples: distance accuracy and normal accuracy are separate goals, and the normal term is what
makes the ReLU network's gradient smooth. Adam with a cosine learning-rate decay; the checkpoint
with the best validation error in the +-1 mm band is kept; runs resume from their checkpoint
(safetensors, no pickle); deterministic under ``seed`` on one device.

The package, one step a module: :mod:`.config` (what a run is asked), :mod:`.data` (the samples
and validation sets), :mod:`.schedule` (steps or the clock, optimiser, threads),
:mod:`.checkpoints` (resumable runs), :mod:`.loop` (:func:`train_neural`) and, for an animation,
:mod:`.deformation` (the deformed preset's fields) and :mod:`.preset_choice` (which animated preset).
"""

from .checkpoints import read_checkpoint_state, save_tensors_atomically
from .config import DEFAULT_STEPS, LEARNING_RATES, NORMAL_WEIGHTS, VALIDATIONS_PER_BUDGET, TrainConfig
from .deformation import DeformationFit, fit_deformation
from .loop import TrainResult, check_preset, train_animated_neural, train_neural
from .preset_choice import PresetChoice, choose_animated_preset, remaining_minutes
from .schedule import RunClock, cosine_learning_rate

__all__ = ["DEFAULT_STEPS", "LEARNING_RATES", "NORMAL_WEIGHTS", "VALIDATIONS_PER_BUDGET", "DeformationFit",
           "PresetChoice", "RunClock", "TrainConfig", "TrainResult", "check_preset", "choose_animated_preset",
           "cosine_learning_rate", "fit_deformation", "read_checkpoint_state", "remaining_minutes", "save_tensors_atomically",
           "train_animated_neural", "train_neural"]
