"""What a validation runs: the profiles (scenes, resolutions, spp ladders,
budgets, failure cases), the scene set and its headers, and which seed every
render uses."""
