"""Training budgets (config overrides) that several test files share, so each is written once.

Every list ends with ``train.compile=false``: ``configs/wargus.yaml`` compiles, a test run does not
pay it off (the other configs do not compile, so it changes nothing there).
"""

TINY = [  # ~2 s: 300 frames, 2 updates of every head, no periodic checkpoint
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=300",
    "train.checkpoint_every=0",
    "train.log_every=300",
    "train.init_random_frames=100",
    "train.batch_size=16",
    "train.updates_per_batch=1",
    "train.buffer_size=1000",
    "train.compile=false",
]

SMALL = [  # ~3 s: 600 frames, 8 updates of every head
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=600",
    "train.checkpoint_every=0",
    "train.log_every=300",
    "train.init_random_frames=200",
    "train.batch_size=32",
    "train.updates_per_batch=2",
    "train.buffer_size=2000",
    "train.compile=false",
]

CHECKPOINTED = [  # the fault tests' run: 3000 frames, a checkpoint every 1000 frames
    "env.num_envs=4",
    "train.frames_per_batch=100",
    "train.total_frames=3000",
    "train.checkpoint_every=1000",
    "train.log_every=500",
    "train.init_random_frames=300",
    "train.batch_size=32",
    "train.updates_per_batch=2",
    "train.buffer_size=5000",
    "train.compile=false",
]

SWEEP_POINT = [  # a windy-fig2 sweep point on top of --quick: ~5 s, averaging already learns a bit
    "train.total_frames=2048",
    "train.init_random_frames=512",
    "train.eps_decay_frames=1024",
    "train.updates_per_batch=8",
    "train.lr=0.005",
    "train.log_every=1024",
    "env.windy.horizon=30",
    "experiment.runs=1",
    "experiment.episodes_per_run=20",
    "eval.batch_size=20",
    "train.compile=false",
]

FIG4 = [  # a small Wargus Figure 4 protocol; a test adds the grid, horizon, runs and trials
    "experiment.learning_episodes_per_trial=8",
    "train.init_random_frames=100",
    "train.batch_size=32",
    "train.frames_per_batch=64",
    "train.buffer_size=5000",
    "heads.hidden=[32]",
    "train.compile=false",
]

CORRIDOR_BUDGET = [  # configs/windy_corridor.yaml's baselines at a test budget: 8192 frames
    "train.total_frames=8192",
    "train.init_random_frames=1000",
    "train.eps_decay_frames=4096",
    "train.updates_per_batch=8",
]
