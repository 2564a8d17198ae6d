#include "gateway/console/console_access.h"

#include <gtest/gtest.h>

namespace sms::gateway::console {
namespace {

using config::Role;

TEST(ConsoleAccess, RolesIncludeTheRightsBelowThem) {
  EXPECT_TRUE(role_allows(Role::Engineer, Role::Operate));
  EXPECT_TRUE(role_allows(Role::Operate, Role::Read));
  EXPECT_TRUE(role_allows(Role::Read, Role::None));
  EXPECT_FALSE(role_allows(Role::Read, Role::Operate));
  EXPECT_FALSE(role_allows(Role::None, Role::Read));
}

TEST(ConsoleAccess, PasswordHashesAreLibsodiumsAndVerify) {
  const std::string hash = hash_password("s3cret");
  EXPECT_TRUE(hash.starts_with("$argon2id$")) << hash;
  EXPECT_TRUE(verify_password(hash, "s3cret"));
  EXPECT_FALSE(verify_password(hash, "s3cret "));
  EXPECT_FALSE(verify_password("$argon2id$garbage", "s3cret"));
  EXPECT_NE(hash_password("s3cret"), hash) << "salted";
}

TEST(ConsoleAccess, LoginChecksNameAndPassword) {
  config::ConsoleConfig console;
  console.users.push_back({"alice", Role::Operate, hash_password("pw-a")});
  const auto alice = check_login(console, "alice", "pw-a");
  ASSERT_TRUE(alice);
  EXPECT_EQ(alice->role, Role::Operate);
  EXPECT_EQ(alice->how, "password");
  EXPECT_FALSE(check_login(console, "alice", "pw-b"));
  EXPECT_FALSE(check_login(console, "bob", "pw-a"));
}

TEST(ConsoleAccess, TokensAreRandomAndComparedWhole) {
  const std::string a = random_token();
  EXPECT_EQ(a.size(), 64u);
  EXPECT_NE(a, random_token());
  EXPECT_TRUE(same_token(a, a));
  EXPECT_FALSE(same_token(a, a.substr(0, 63)));
  EXPECT_FALSE(same_token("", ""));
}

TEST(ConsoleAccess, SessionsExpireAndAreBounded) {
  SessionStore store(std::chrono::seconds{60}, 2);
  const auto t0 = SteadyClock::time_point{} + std::chrono::hours{1};
  const Session first = store.create({"a", Role::Read, "password"}, t0);
  EXPECT_NE(first.csrf, first.token);
  ASSERT_TRUE(store.find(first.token, t0 + std::chrono::seconds{59}));
  // Touched at 59 s: alive until 119 s.
  EXPECT_TRUE(store.find(first.token, t0 + std::chrono::seconds{118}));
  EXPECT_FALSE(store.find(first.token, t0 + std::chrono::seconds{179}));
  const Session b = store.create({"b", Role::Read, "password"}, t0);
  const Session c = store.create({"c", Role::Read, "password"}, t0 + std::chrono::seconds{1});
  const Session d = store.create({"d", Role::Read, "password"}, t0 + std::chrono::seconds{2});
  EXPECT_EQ(store.size(), 2u);
  EXPECT_FALSE(store.find(b.token, t0 + std::chrono::seconds{3})) << "the least recently used goes";
  EXPECT_TRUE(store.find(c.token, t0 + std::chrono::seconds{3}));
  store.remove(d.token);
  EXPECT_FALSE(store.find(d.token, t0 + std::chrono::seconds{3}));
}

TEST(ConsoleAccess, WithoutUsersOrCertificatesTheLoopbackUserReadsOnly) {
  EXPECT_EQ(implicit_principal({}, true).role, Role::Read);
  EXPECT_EQ(implicit_principal({}, false).role, Role::None);
  EXPECT_EQ(implicit_principal({.local_every_right = true}, true).role, Role::Engineer);
  EXPECT_EQ(implicit_principal({.local_every_right = true}, false).role, Role::None);
  EXPECT_EQ(implicit_principal({.users = true}, true).role, Role::None) << "users configured: log in";
  EXPECT_EQ(implicit_principal({.certificates = true}, true).role, Role::None);
}

}  // namespace
}  // namespace sms::gateway::console
