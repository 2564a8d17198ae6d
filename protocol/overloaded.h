#pragma once
// std::visit with one lambda per alternative: std::visit(Overloaded{[](const A&) {...}, ...}, v).
namespace sms {

template <typename... Fs>
struct Overloaded : Fs... {
  using Fs::operator()...;
};
template <typename... Fs>
Overloaded(Fs...) -> Overloaded<Fs...>;

}  // namespace sms
