"""First-party plugin with small physics-free parts: the sine controller and the evaluate optimizer."""
