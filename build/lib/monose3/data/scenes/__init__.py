"""Domain-randomised synthetic scenes (``monose3 generate``): profiles, sampling, appearance, the writer."""
