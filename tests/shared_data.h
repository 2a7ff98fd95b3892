// Where the tests find the real data of shared/data, and how a test that needs it skips.
#pragma once

#include <gtest/gtest.h>

#include <filesystem>
#include <string>

namespace mocap::testing {

inline std::string SharedData() { return MOCAP_SHARED_DATA; }

}  // namespace mocap::testing

#define SKIP_WITHOUT_SHARED_DATA()                                                                  \
  do {                                                                                               \
    if (!std::filesystem::is_directory(::mocap::testing::SharedData())) {                           \
      GTEST_SKIP() << "shared data folder " << ::mocap::testing::SharedData()                        \
                   << " is absent (CI puts shared/ beside the checkout); skipping real-data test"; \
    }                                                                                                \
  } while (0)
