// What the C++ shims return to Rust: nullptr, or a message the caller frees with
// `rlmflow_free_message`; no C++ exception crosses into Rust.
#pragma once

#include <cstdlib>
#include <cstring>
#include <exception>

template <typename F>
char* guarded(F f) {
  try {
    f();
    return nullptr;
  } catch (const std::exception& e) {
    return strdup(e.what());
  } catch (...) {
    return strdup("an unknown C++ exception");
  }
}
