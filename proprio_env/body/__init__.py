"""The simulated body (MuJoCo): where the elbow model lives and how it is loaded (`model`), its
exact muscle lengths (`muscle_length`), the fits of the length model and of the moment arms
made from it (`length_fitting`, `moment_arm_fitting`), the servo's motion (`servo_motion`) and
the simulated AX-12 readings of angle and load (`encoder`). Nothing here runs on the
prosthesis: that is :mod:`spindle.chain`."""
