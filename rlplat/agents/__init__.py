"""Learning agents and the policies they are measured against: SAC from TorchRL parts
(:mod:`~rlplat.agents.sac`), replay transitions, checkpoints, scripted and network policies
(:mod:`~rlplat.agents.policies`)."""
