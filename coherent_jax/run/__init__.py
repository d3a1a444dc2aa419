"""Running a training: everything between a parsed config and a finished run directory.

The launch helpers shared by ``train`` and ``sweep`` (`launch`, with a single run's own path
in `single`), the host loop (`loop`, its records in `loop_state`), the run directory and its
checkpoints (`runs`, `rundir`, `runlock`, `provenance`), what a run writes beside them
(`tracking` for Weights & Biases, `tb_events` for TensorBoard, `video`), the guards
(`divergence`, `memory`) and the devices and processes (`sharding`, `multihost`). Nothing
here is learning code: the trainers are `coherent_jax.agents`'s.
"""
