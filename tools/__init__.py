"""Repository-only scripts (not installed with nerfpod): `python -m tools.pod_tables`, tools.topology,
tools.scene_report, tools.view_benchmark, and the accelerator check (tools/device_check.sh)."""
