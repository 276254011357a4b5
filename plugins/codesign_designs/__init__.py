"""First-party design representations (SoftZoo appendix): how trainable parameters become a robot body."""
