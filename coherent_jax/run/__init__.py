"""Running a training: everything between a parsed config and a finished run directory.

The launch path shared by ``train`` and ``sweep`` (`launch`, no JAX) and what it runs once the
input is checked (`training`: a single run, or a sweep's grid of `sweep` as one program); the
host loop (`loop`, its records and what stops it in `loop_state`); the run directory
(`rundir`), its checkpoint and stored config (`checkpoint`); what a run gives out as it goes
(`outputs`: callbacks, Weights & Biases, videos' format; `tb_events` for TensorBoard); the
devices and processes (`devices`, `multihost`) and the memory check (`memory`); the evaluation
and its video (`evaluation`, `policy`). Nothing here is learning code: the trainers are
`coherent_jax.agents`'s.
"""
