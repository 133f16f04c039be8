"""User tools that are not the trainer (`python -m tools.export ...`)."""
