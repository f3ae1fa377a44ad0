"""Meta-World's scripted experts (`metaworld.policies`) as a policy: each task's hand-written
controller, reading Meta-World's whole state. No network: it checks the Meta-World integration end
to end (wrong image flips are outside its view, but wrong action scaling, state or success detection
make the experts fail) and gives the simulator-only speed of Meta-World."""
