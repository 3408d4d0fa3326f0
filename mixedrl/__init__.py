"""mixedrl: mixed reinforcement learning with additive stochastic uncertainty.

Implements Mu et al., *Mixed Reinforcement Learning with Additive Stochastic Uncertainty*. Equation
numbers ``eq. (N)`` everywhere in this package follow ``shared/paper/EQUATIONS.md``.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
