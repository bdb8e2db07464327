"""The dataset: plan a build, run its episodes in parallel, write and check the shards.

Modules (data flows down):
    plan.py         which episodes a build holds, from its arguments alone
    executors.py    a supervised process pool or Ray, for every parallel command
    shards.py       writing one episode's Parquet shard (temporary name, then rename)
    manifest.py     the build's manifest, lock and resume
    build.py        `datagen build`
    validate.py     `datagen validate`
    inspect.py      `datagen inspect` (frames, videos)
    recording.py    Rerun recordings of an episode
"""
