"""What every family's env shares: the batched env base (:mod:`.batched`), the Gymnasium env
over it (:mod:`.gym_env`), one episode per sub-environment (:mod:`.episodes`), Gymnasium's checks (:mod:`.gym_checks`) and the registration of the
families' Gymnasium ids (:mod:`.registration`).
The families' own envs live in their packages (``taskvar_torch.families.<name>``)."""
