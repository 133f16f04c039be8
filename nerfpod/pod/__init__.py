"""The pod concern: what a config costs on a TPU pod, known before the pod is paid for, from any machine.

    chips     the Cloud TPU chips' published figures (peak FLOP/s, HBM, bandwidths) and the pods nerfpod
              knows by accelerator type (v4-32, v5e-64, ...): their topologies, chips and hosts
    hlo_cost  HloProgram: a roofline time estimate of a compiled XLA program, op by op, on a chip's peaks
    aot       `nerfpod aot` (also `python -m nerfpod.pod.aot`): a config's train step and renderers compiled
              ahead of time for a pod's topology with XLA's TPU compiler (libtpu), and the report of their
              memory per chip, estimated time, rays/s and collectives

The launchers' preflight (launch/preflight.py) and the pod tables (tools/pod_tables.py) run `aot`; the
launchers read `chips` for a pod's size (it imports the standard library only, as this package does).
"""
