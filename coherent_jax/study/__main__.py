"""``python -m coherent_jax.study``: the command (`coherent_jax.study.command`)."""

import sys

from coherent_jax.study.command import main

if __name__ == "__main__":
    sys.exit(main())
