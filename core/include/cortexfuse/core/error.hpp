#pragma once
// Typed errors of the core. One style for the whole layer: exceptions.
// Every message names the input (a file, a field) and the problem, in one line,
// so the CLI can print it as is and the daemon can put it in a 4xx body.
#include <stdexcept>
#include <string>

namespace cf {

/// Bad input from outside: a missing or corrupt file, an invalid field.
class InputError : public std::runtime_error {
public:
    InputError(const std::string& what_input, const std::string& problem)
        : std::runtime_error(what_input + ": " + problem), input_(what_input) {}
    const std::string& input() const { return input_; }

private:
    std::string input_;
};

/// A long operation was cancelled through its CancelToken.
class Cancelled : public std::runtime_error {
public:
    Cancelled() : std::runtime_error("cancelled") {}
};

}  // namespace cf
