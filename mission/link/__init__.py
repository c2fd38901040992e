"""The link to Earth: the contact plan, the onboard downlink queue, the bridge between the
rover's network and the ground's, commands at the step boundary, the ground station and the
link's certificates."""
