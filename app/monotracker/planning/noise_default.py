"""The planner's default image noise, in a module of its own so that the CLI's parser can say it
without importing the science stack."""

#: default image noise of the ball centres, px (1-sigma per coordinate): the centre error the
#: edge-fitted detector shows on physically rendered frames (the committed Mitsuba tuning crops,
#: whole balls, mean over 4 frames: 0.16 / 0.21 / 0.32 px OR / clean / degraded; edge spread
#: 0.15-0.26 px); near the upper end, so that the plan is not optimistic
DEFAULT_NOISE_PX = 0.3
