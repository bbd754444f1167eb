"""The presets' names, from quickest to the paper's schedule. This module imports nothing, so the command lines
can offer them without loading torch; ``ops.config.presets`` refuses to import when its ``PRESETS`` disagree."""

PRESET_NAMES = ("draft", "standard", "fast", "paper")
