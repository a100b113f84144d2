/*
 * Stand-ins for the parts of Unreal Engine that bindings/unreal/Flame uses, so that its C++
 * compiles with g++ and its component runs against the real libflame outside the engine
 * (tests/bindings/unreal/test_component.cpp). Same names and call shapes as the engine; the
 * behaviour is only what the plugin relies on. TCHAR is char16_t as on Linux, so TCHAR/UTF-8
 * mix-ups fail to compile here as they would there.
 */
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdarg>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

typedef char16_t TCHAR;
typedef char ANSICHAR;
typedef uint8_t uint8;
typedef int32_t int32;
typedef uint32_t uint32;
typedef int64_t int64;
typedef uint64_t uint64;

#define TEXT(s) u##s
#define FLAME_API
#define PLATFORM_WINDOWS 0
#define UCLASS(...)
#define USTRUCT(...)
#define UENUM(...)
#define UMETA(...)
#define UPROPERTY(...)
#define UFUNCTION(...)
/* The access after it stays the default, as in the engine: private in a UCLASS (the engine's
 * ends in private:), public in a USTRUCT (the engine's changes none). Super is used only by
 * the component. */
#define GENERATED_BODY() typedef UActorComponent Super;

namespace ue_stub {
inline std::u16string FromUtf8(const char* s) {
    std::u16string out;
    for (const unsigned char* p = (const unsigned char*)s; p && *p;) {
        uint32_t c = *p++;
        int extra = c >= 0xF0 ? 3 : c >= 0xE0 ? 2 : c >= 0xC0 ? 1 : 0;
        if (extra) c &= (0x3F >> extra);
        for (; extra > 0 && *p; extra--) c = (c << 6) | (*p++ & 0x3F);
        if (c >= 0x10000) {
            c -= 0x10000;
            out += (char16_t)(0xD800 + (c >> 10));
            out += (char16_t)(0xDC00 + (c & 0x3FF));
        } else {
            out += (char16_t)c;
        }
    }
    return out;
}
inline std::string ToUtf8(const char16_t* s) {
    std::string out;
    for (; s && *s; s++) {
        uint32_t c = *s;
        if (c >= 0xD800 && c < 0xDC00 && s[1]) c = 0x10000 + ((c - 0xD800) << 10) + (*++s - 0xDC00);
        if (c < 0x80) out += (char)c;
        else if (c < 0x800) { out += (char)(0xC0 | (c >> 6)); out += (char)(0x80 | (c & 0x3F)); }
        else if (c < 0x10000) { out += (char)(0xE0 | (c >> 12)); out += (char)(0x80 | ((c >> 6) & 0x3F)); out += (char)(0x80 | (c & 0x3F)); }
        else { out += (char)(0xF0 | (c >> 18)); out += (char)(0x80 | ((c >> 12) & 0x3F)); out += (char)(0x80 | ((c >> 6) & 0x3F)); out += (char)(0x80 | (c & 0x3F)); }
    }
    return out;
}
struct FromUtf8Temp { std::u16string s; operator const TCHAR*() const { return s.c_str(); } };
struct ToUtf8Temp { std::string s; operator const ANSICHAR*() const { return s.c_str(); } };
}  // namespace ue_stub

#define UTF8_TO_TCHAR(s) (const TCHAR*)ue_stub::FromUtf8Temp{ue_stub::FromUtf8(s)}

/* The converter behind TCHAR_TO_UTF8, for a UTF-8 copy that lives as long as it does. Get()
 * returns UTF8CHAR* in UE5 (char here): callers cast it to const ANSICHAR*. */
class FTCHARToUTF8 {
public:
    explicit FTCHARToUTF8(const TCHAR* s) : s_(ue_stub::ToUtf8(s)) {}
    const char* Get() const { return s_.c_str(); }
    int32_t Length() const { return (int32_t)s_.size(); }
    FTCHARToUTF8(const FTCHARToUTF8&) = delete;
private:
    std::string s_;
};
#define TCHAR_TO_UTF8(s) (const ANSICHAR*)ue_stub::ToUtf8Temp{ue_stub::ToUtf8(s)}

template <typename T> struct TArray {
    std::vector<T> v;
    TArray() = default;
    int32 Num() const { return (int32)v.size(); }
    void SetNum(int32 n) { v.resize((size_t)n); }
    T* GetData() { return v.data(); }
    const T* GetData() const { return v.data(); }
    void Add(const T& x) { v.push_back(x); }
    void Append(const T* p, int32 n) { v.insert(v.end(), p, p + n); }
    void SetNumUninitialized(int32 n) { v.resize((size_t)n); }
    void RemoveAt(int32 i, int32 n = 1) { v.erase(v.begin() + i, v.begin() + i + n); }
    void Reset() { v.clear(); }
    T& operator[](int32 i) { return v[(size_t)i]; }
    const T& operator[](int32 i) const { return v[(size_t)i]; }
};

class FString {
public:
    FString() = default;
    FString(const TCHAR* s) : s_(s ? s : u"") {}
    const TCHAR* operator*() const { return s_.c_str(); }
    bool operator==(const FString& o) const { return s_ == o.s_; }
    bool IsEmpty() const { return s_.empty(); }
    void Reset() { s_.clear(); }
    int32 Len() const { return (int32)s_.size(); }
    FString operator+(const FString& o) const { FString r(*this); r.s_ += o.s_; return r; }
    std::string Utf8() const { return ue_stub::ToUtf8(s_.c_str()); }
    /* %s takes const TCHAR*, %d int, %u unsigned: what the plugin formats. */
    static FString Printf(const TCHAR* fmt, ...) {
        va_list ap;
        va_start(ap, fmt);
        FString r = VPrintf(fmt, ap);
        va_end(ap);
        return r;
    }
    static FString VPrintf(const TCHAR* fmt, va_list ap) {
        std::u16string out;
        for (const TCHAR* p = fmt; *p; p++) {
            if (*p != u'%' || !p[1]) { out += *p; continue; }
            switch (*++p) {
                case u's': { const TCHAR* a = va_arg(ap, const TCHAR*); out += a ? a : u"(null)"; break; }
                case u'd': out += ue_stub::FromUtf8(std::to_string(va_arg(ap, int)).c_str()); break;
                case u'u': out += ue_stub::FromUtf8(std::to_string(va_arg(ap, unsigned)).c_str()); break;
                default: out += u'%'; out += *p;
            }
        }
        FString r;
        r.s_ = out;
        return r;
    }
private:
    std::u16string s_;
};

template <typename T> void Swap(T& a, T& b) { std::swap(a, b); }

/* UE5's math types hold doubles. */
struct FQuat {
    double X = 0, Y = 0, Z = 0, W = 1;
    FQuat() = default;
    FQuat(double x, double y, double z, double w) : X(x), Y(y), Z(z), W(w) {}
    static const FQuat Identity;
};
inline const FQuat FQuat::Identity{0, 0, 0, 1};
struct FVector {
    double X = 0, Y = 0, Z = 0;
    FVector() = default;
    FVector(double x, double y, double z) : X(x), Y(y), Z(z) {}
    static const FVector ZeroVector;
};
inline const FVector FVector::ZeroVector{0, 0, 0};

struct FMath {
    template <typename T> static T Max(T a, T b) { return a < b ? b : a; }
};

/* Names, transforms and a skeletal mesh's reference skeleton (UE 5.1+: USkinnedAsset), and a
 * poseable mesh whose bone-space transforms the plugin writes; the test builds them. */
class FName {
public:
    FName() = default;
    explicit FName(const TCHAR* s) : s_(s) {}
    FString ToString() const { return s_; }
private:
    FString s_;
};
struct FTransform {
    FQuat Rotation;
    FVector Translation;
    FVector Scale3D{1, 1, 1};
    FTransform() = default;
    FTransform(const FQuat& R, const FVector& T, const FVector& S) : Rotation(R), Translation(T), Scale3D(S) {}
    FQuat GetRotation() const { return Rotation; }
    FVector GetTranslation() const { return Translation; }
    FVector GetScale3D() const { return Scale3D; }
    static const FTransform Identity;
};
inline const FTransform FTransform::Identity{};
struct FReferenceSkeleton {
    TArray<FName> Names;
    TArray<int32> Parents;
    TArray<FTransform> Pose;
    int32 GetNum() const { return Names.Num(); }
    FName GetBoneName(int32 i) const { return Names[i]; }
    int32 GetParentIndex(int32 i) const { return Parents[i]; }
    const TArray<FTransform>& GetRefBonePose() const { return Pose; }
};
class USkinnedAsset {
public:
    FReferenceSkeleton RefSkeleton;
    const FReferenceSkeleton& GetRefSkeleton() const { return RefSkeleton; }
};
class UPoseableMeshComponent {
public:
    USkinnedAsset* Asset = nullptr;
    USkinnedAsset* GetSkinnedAsset() const { return Asset; }
    TArray<FTransform> BoneSpaceTransforms;
    int32 RefreshCount = 0; /* MarkRefreshTransformDirty calls, for the test */
    void MarkRefreshTransformDirty() { RefreshCount++; }
};
struct FMemory {
    template <typename T> static void Memzero(T& x) { std::memset((void*)&x, 0, sizeof(T)); }
};

enum class ESPMode { NotThreadSafe, ThreadSafe };
template <typename T, ESPMode Mode = ESPMode::ThreadSafe> struct TSharedPtr {
    std::shared_ptr<T> p;
    TSharedPtr() = default;
    TSharedPtr(std::shared_ptr<T> q) : p(std::move(q)) {}
    bool IsValid() const { return (bool)p; }
    void Reset() { p.reset(); }
    T* operator->() const { return p.get(); }
    T& operator*() const { return *p; }
};
template <typename T, ESPMode Mode = ESPMode::ThreadSafe, typename... A> TSharedPtr<T, Mode> MakeShared(A&&... a) {
    return TSharedPtr<T, Mode>(std::make_shared<T>(std::forward<A>(a)...));
}

class FCriticalSection {
public:
    void Lock() { m_.lock(); }
    void Unlock() { m_.unlock(); }
private:
    std::mutex m_;
};
class FScopeLock {
public:
    explicit FScopeLock(FCriticalSection* c) : c_(c) { c_->Lock(); }
    ~FScopeLock() { c_->Unlock(); }
    FScopeLock(const FScopeLock&) = delete;
private:
    FCriticalSection* c_;
};
class FThreadSafeCounter {
public:
    int32 Increment() { return ++v_; }
    int32 Decrement() { return --v_; }
    int32 GetValue() const { return v_; }
private:
    std::atomic<int32> v_{0};
};

enum class EAsyncExecution { TaskGraph, Thread, ThreadPool };
/* Counts the threads Async starts that are still running, so a test can wait for them. */
inline std::atomic<int>& UeStubRunningThreads() { static std::atomic<int> n{0}; return n; }
template <typename F> void Async(EAsyncExecution, F&& f) {
    UeStubRunningThreads()++;
    std::thread([fn = std::forward<F>(f)]() mutable {
        {
            F local(std::move(fn));  // destroyed (with what it holds) before the count drops
            local();
        }
        UeStubRunningThreads()--;
    }).detach();
}

struct FPaths {
    static bool IsRelative(const FString& p) { return p.Len() == 0 || (*p)[0] != u'/'; }
    static FString Combine(const FString& a, const FString& b) { return a + FString(u"/") + b; }
    static FString ProjectContentDir() { return FString(u"/project/Content"); }
    static FString ConvertRelativePathToFull(const FString& p) { return p; }
};

/* Logging: categories are names; UE_LOG prints "Category: Verbosity: message" and keeps the
 * line, so a test can check what was logged (UeStubLogLines). */
struct FLogCategory { const char* name; };
#define DECLARE_LOG_CATEGORY_EXTERN(Name, Default, Compile) extern FLogCategory Name
#define DEFINE_LOG_CATEGORY(Name) FLogCategory Name{#Name}
namespace ue_stub {
inline std::mutex& LogLock() { static std::mutex m; return m; }
inline std::vector<std::string>& LogLines() { static std::vector<std::string> lines; return lines; }
inline void Log(const char* category, const char* verbosity, const std::string& message) {
    std::string line = std::string(category) + ": " + verbosity + ": " + message;
    std::fprintf(stderr, "%s\n", line.c_str());
    std::lock_guard<std::mutex> guard(LogLock());
    LogLines().push_back(line);
}
}  // namespace ue_stub
inline std::vector<std::string> UeStubLogLines() {
    std::lock_guard<std::mutex> guard(ue_stub::LogLock());
    return ue_stub::LogLines();
}
#define UE_LOG(Category, Verbosity, Fmt, ...) \
    ue_stub::Log(Category.name, #Verbosity, FString::Printf(Fmt, ##__VA_ARGS__).Utf8())

class IModuleInterface {
public:
    virtual ~IModuleInterface() = default;
    virtual void StartupModule() {}
    virtual void ShutdownModule() {}
};
IModuleInterface* UeStubModule();
struct FModuleManager {
    template <typename T> static T& LoadModuleChecked(const char*) { return *static_cast<T*>(UeStubModule()); }
};
#define IMPLEMENT_MODULE(Class, Name) \
    IModuleInterface* UeStubModule() { static Class m; return &m; }

class IPlugin {
public:
    FString GetBaseDir() const { return FString(u"/project/Plugins/Flame"); }
};
class IPluginManager {
public:
    static IPluginManager& Get() { static IPluginManager m; return m; }
    TSharedPtr<IPlugin> FindPlugin(const TCHAR*) { return TSharedPtr<IPlugin>(std::make_shared<IPlugin>()); }
};
struct FPlatformProcess {
    static void* GetDllHandle(const TCHAR*) { return nullptr; }
    static void FreeDllHandle(void*) {}
};

/* Components. */
enum ELevelTick { LEVELTICK_All };
struct FActorComponentTickFunction { bool bCanEverTick = false; };
namespace EEndPlayReason { enum Type { Destroyed, LevelTransition, EndPlayInEditor, RemovedFromWorld, Quit }; }
class UActorComponent {
public:
    virtual ~UActorComponent() = default;
    virtual void BeginPlay() {}
    virtual void TickComponent(float, ELevelTick, FActorComponentTickFunction*) {}
    virtual void EndPlay(const EEndPlayReason::Type) {}
    FActorComponentTickFunction PrimaryComponentTick;
};

#define DECLARE_DYNAMIC_MULTICAST_DELEGATE(Name) \
    struct Name { std::vector<std::function<void()>> fns; void AddLambda(std::function<void()> f) { fns.push_back(f); } \
                  void Broadcast() { for (auto& f : fns) f(); } };
#define DECLARE_DYNAMIC_MULTICAST_DELEGATE_OneParam(Name, T1, N1) \
    struct Name { std::vector<std::function<void(T1)>> fns; void AddLambda(std::function<void(T1)> f) { fns.push_back(f); } \
                  void Broadcast(T1 a) { for (auto& f : fns) f(a); } };
#define DECLARE_DYNAMIC_MULTICAST_DELEGATE_TwoParams(Name, T1, N1, T2, N2) \
    struct Name { std::vector<std::function<void(T1, T2)>> fns; void AddLambda(std::function<void(T1, T2)> f) { fns.push_back(f); } \
                  void Broadcast(T1 a, T2 b) { for (auto& f : fns) f(a, b); } };
