"""Robot owners' datasets: the registry, opening and loading them, the decoded-frame cache, generated assets."""
