"""Running predictors on a stream: the game-engine Session, the local server, its protocol and client."""
