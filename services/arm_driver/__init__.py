"""Arm driver: Dobot CR5 TCP/IP client, Ruckig jerk-limited streaming and safety limits."""
