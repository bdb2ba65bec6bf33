"""Many arms: the roster and the Zenoh routers' access control it makes (acl), a router of eclipse-zenoh's own
(router), and the fleet's view of every robot that answers (status)."""
