// How gdrf's C++ bridges (dist/c10d.cpp, nn/sine.cpp) report failure across their C
// interfaces: every C++ exception is caught and its message copied into the caller's buffer,
// so nothing aborts or unwinds into Rust.
#pragma once

#include <c10/util/Exception.h>

#include <algorithm>
#include <cstring>
#include <exception>
#include <string>

namespace gdrf {

inline void say(char* err, size_t len, const std::string& msg) {
  if (err == nullptr || len == 0) return;
  size_t n = std::min(len - 1, msg.size());
  std::memcpy(err, msg.data(), n);
  err[n] = '\0';
}

// Runs `f`; 0 if it returned, 1 with the exception's message in `err` if it threw.
template <typename F>
int guarded(char* err, size_t len, F f) {
  try {
    f();
    return 0;
  } catch (const c10::Error& e) {
    // Without the C++ stack trace that what() appends.
    say(err, len, e.what_without_backtrace());
  } catch (const std::exception& e) {
    say(err, len, e.what());
  } catch (...) {
    say(err, len, "unknown C++ exception");
  }
  return 1;
}

}  // namespace gdrf
