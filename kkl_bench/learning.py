"""What a learned estimator plugin trains with, so that its row gets the care every
built-in learned row gets (protocol section 6.5).

- :func:`budget`: its settings from the profile's budget, with the defaults of its own
  dataclass for every key the profile does not know (a new plugin's name is in no
  profile: it gets the profile's ``default`` table, whose keys its dataclass may not
  have).
- :func:`train`: Adam under the plateau rule (:class:`PlateauRule`, read from the
  budget): the validation error measured as it goes, the learning rate lowered on each
  plateau, the training stopped on the last and ended at its best state. Its
  :meth:`Training.log` is the training log the board reads (validation curve, why it
  stopped: the Converged column).
- :func:`cached`: the model trained once per description and kept in the run's model
  cache (``FitContext.cache_dir``), so that ``kkl-bench run`` on other tracks and
  ``kkl-bench cost`` load it instead of training again; a killed training continues
  from its checkpoint.

The README's plugin package ("A plugin package: a new system and a learned estimator")
shows all three in one plugin.
"""

from __future__ import annotations

from kkl_bench.kkl.config import from_budget as budget
from kkl_bench.kkl.optimize import Training
from kkl_bench.kkl.optimize import minimize as train
from kkl_bench.kkl.phase2 import load_or_train as cached
from kkl_bench.kkl.plateau import PlateauRule

__all__ = ["PlateauRule", "Training", "budget", "cached", "train"]
