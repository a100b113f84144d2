// Just enough of UnityEngine's surface to compile bindings/csharp/FlameExample.cs (and Flame.cs
// with UNITY_5_3_OR_NEWER defined) outside Unity and drive it from FlameExampleTest.cs.
using System;

namespace UnityEngine
{
    public class Object { }
    public class Component : Object { }
    public class Behaviour : Component { }
    public class MonoBehaviour : Behaviour { }
    public class TextAsset : Object { public byte[] bytes { get { return null; } } }
    public static class Application { public static string streamingAssetsPath { get { return ""; } } }
    public static class Debug { public static void LogError(object message) { Console.Error.WriteLine("Debug.LogError: " + message); } }
    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string tooltip) { } }
}

namespace AOT
{
    // In Unity this lives in UnityEngine.dll; Flame.cs defines it only outside Unity.
    [AttributeUsage(AttributeTargets.Method)]
    public sealed class MonoPInvokeCallbackAttribute : Attribute { public MonoPInvokeCallbackAttribute(Type type) { } }
}
