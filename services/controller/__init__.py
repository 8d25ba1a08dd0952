"""Controller: MPC shape servoing along the planned SOI path with an online Broyden Jacobian."""
