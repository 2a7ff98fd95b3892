// Helpers shared by the tests of the simulated subject (test_sim: the recorded session;
// test_live_scene: the live subject).
#pragma once
#include <gtest/gtest.h>

#include <string>

#include "formats/marker_data.h"
#include "sim/protocol.h"

namespace mocap::sim {

// Every required excitation of `movement` reached in `table` — and not wildly beyond it (8 deg):
// the simulated subject does what the protocol asks, not more.
inline void ExpectExcitationsReached(const Movement& movement,
                                     const formats::CoordinateTable& table,
                                     const std::string& context) {
  for (const ExcitationCheck& c : CheckExcitations(movement, table)) {
    if (!c.required) continue;
    EXPECT_TRUE(c.ok) << context << " " << movement.name << " " << c.coordinate << ": reached ["
                      << c.reached_min_deg << ", " << c.reached_max_deg << "], required ["
                      << c.min_deg << ", " << c.max_deg << "]";
    EXPECT_GT(c.reached_min_deg, c.min_deg - 8) << movement.name << " " << c.coordinate;
    EXPECT_LT(c.reached_max_deg, c.max_deg + 8) << movement.name << " " << c.coordinate;
  }
}

}  // namespace mocap::sim
