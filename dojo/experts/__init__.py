"""The scripted experts: the privileged `oracle` policy, its skill library and motion planning, and task validity."""
