"""The persistent state of a deployment as the methods see it: the one database + blob
container (:mod:`~service.store.container`) and the actor store (:mod:`~service.store.actors`:
canonical actor, layout and clip blobs, read back as :class:`~service.methods.inputs.ActorData`
and :class:`~service.methods.inputs.Clip`). Below the jobs and the application layer."""
