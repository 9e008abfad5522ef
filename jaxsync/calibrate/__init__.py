"""Your robot's servo and command delay from a recording: the trajectory to play (``excite``), the
replay of recorded commands (``replay``), the fit with MuJoCo's identification toolbox (``fit``) and the
two jobs the command line runs (``jobs``); docs/calibrate.md."""
