"""Learning: PPO losses and GAE, the Learner (model + optimiser + update + state), rollouts, the local trainer."""
