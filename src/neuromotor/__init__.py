"""neuromotor: motion perturbation with simple neuromotor control models (Yin, Cline & Pai 2003).

Physics runs in float64: importing the package turns on ``jax_enable_x64``.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
