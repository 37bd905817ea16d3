"""Layer 6: what the command line shows its user after a job: the closing summary of each job and the
report page of a conceal or verify run. Imports every layer below; only conceal_jax.main imports it."""
