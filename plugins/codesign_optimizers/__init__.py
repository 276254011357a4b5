"""First-party optimizers: differentiable physics (Adam), CMA-ES, PPO; design, control or both."""
